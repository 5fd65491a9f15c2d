"""The errors of the models layer. The command lines print them as one ``error:`` line (exit 2); this package
never depends on them."""


class ModelError(Exception):
    """A network cannot be built or loaded from what was given (named in the message)."""


class CheckpointError(ModelError):
    """A checkpoint is missing, corrupt, holds NaN weights, or does not match the architecture it claims."""


class TeacherError(ModelError):
    """A teacher network is unknown, or its weight file is missing or unreadable."""
