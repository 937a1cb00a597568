"""The fleet's places: where each device is (what its own messages report, else the places file ``--fleet``, else
the service's ``--location``) and what the World Magnetic Model expects there (``places``). Above the wire (a places
file's keys are device ids, checked as the wire checks them) and below the compass and the calibrator, which both
keep one. Pure."""
