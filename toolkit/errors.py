"""The one exception type the CLI turns into a one-line error and exit code 2."""


class ToolkitError(Exception):
    """A user-facing failure: bad input, missing file, failed verification.

    The CLI prints ``error: <message>`` on one line and exits with code 2; no traceback.
    """
