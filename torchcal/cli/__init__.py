"""The ``torchcal`` command line: ``calibrate``, ``loop``, ``correct``, ``fleet``, ``plan``."""
