"""The error of the export layer: an export that cannot be made or fails its checks (graph, profile, parity).
The command lines print it as one ``error:`` line (exit 2); this package never depends on them."""


class ExportError(Exception):
    """An export setting, input or check failed; nothing was written (named in the message)."""
