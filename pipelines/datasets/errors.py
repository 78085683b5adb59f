"""The error every reader raises for a bad input file: one line naming the file and what is wrong, which the
commands print as it is (exit code 2)."""


class CaptureError(ValueError):
    """A capture file is missing or malformed; the message names the file and the problem."""
