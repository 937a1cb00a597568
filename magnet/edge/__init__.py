"""The edge's pure parts: the loop that reads a sensor until it gives a usable sample (``readloop``) and a
recording played back at its own pace (``replay``). The process is ``services.edge``."""
