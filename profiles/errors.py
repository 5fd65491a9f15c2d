"""The error of the profiles layer: a profile that cannot be read or holds a value no target can have. The
command lines print it as one ``error:`` line (exit 2); this package never depends on them."""


class ProfileError(Exception):
    """A target profile is unknown, unreadable, or has a missing or invalid field (named in the message)."""
