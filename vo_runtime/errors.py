"""Errors raised by vo_runtime. Apps embedding the runtime catch `VORuntimeError`."""


class VORuntimeError(Exception):
    """Base class: a clear, one-line reason (bad artefact, bad calibration, bad frame)."""


class ArtefactError(VORuntimeError):
    """The artefact directory is missing, incomplete, or fails its checksum."""


class CalibrationError(VORuntimeError):
    """The camera calibration is missing, malformed, or does not fit the frames."""
