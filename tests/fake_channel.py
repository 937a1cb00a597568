"""A stand-in for a Zenoh FIFO channel handler, for the intakes' pump loops (no network)."""

from __future__ import annotations


class ClosedError(Exception):
    pass


class FakeChannel:
    """recv gives the next sample or raises ClosedError at the end; try_recv gives None when nothing waits (a None
    among the samples is such a pause: the batch being drained ends there)."""

    def __init__(self, samples):
        self.samples = list(samples)

    def recv(self):
        if not self.samples:
            raise ClosedError
        return self.samples.pop(0)

    def try_recv(self):
        return self.samples.pop(0) if self.samples and self.samples[0] is not None else self._gap()

    def _gap(self):
        if self.samples and self.samples[0] is None:
            self.samples.pop(0)  # a pause: the batch ends here
