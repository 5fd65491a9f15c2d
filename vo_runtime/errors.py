"""Errors raised by vo_runtime. Apps embedding the runtime catch `VORuntimeError`."""
from __future__ import annotations

MESSAGE_LIMIT = 240  # characters of a foreign exception's text quoted in one of our one-line messages


class VORuntimeError(Exception):
    """Base class: a clear, one-line reason (bad artefact, bad calibration, bad frame)."""


class ArtefactError(VORuntimeError):
    """The artefact directory is missing, incomplete, or fails its checksum."""


class CalibrationError(VORuntimeError):
    """The camera calibration is missing, malformed, or does not fit the frames."""


class FrameError(VORuntimeError):
    """A frame cannot be used: undecodable, empty, of an unusable shape or dtype, or holding NaN/inf."""


class TimestampError(VORuntimeError):
    """A timestamp is not a finite number, or does not come after the previous frame's."""


class ConcurrentUseError(VORuntimeError):
    """One VO instance was entered from a second thread while another was inside it."""


def first_line(exc: BaseException, limit: int | None = MESSAGE_LIMIT) -> str:
    """The first non-blank line of ``str(exc)``, shortened to ``limit`` (None: never); the class name when the
    text is empty.

    Foreign exceptions (torch, onnxruntime, OpenCV) may carry empty or many-line messages; ours are one line.
    """
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    text = lines[0] if lines else type(exc).__name__
    return text if limit is None or len(text) <= limit else text[: limit - 3] + "..."
