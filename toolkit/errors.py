"""The one exception type the CLI turns into a one-line error and exit code 2."""


class ToolkitError(Exception):
    """A user-facing failure: bad input, missing file, failed verification.

    The CLI prints ``error: <message>`` on one line and exits with code 2; no traceback.
    """


def run_module_main(main) -> None:
    """``python -m`` entry of a module outside the CLI (``main() -> int``): exits with its code, and turns a
    `ToolkitError`, a `models.errors.ModelError` or a ValueError into the CLI's one-line ``error:`` and exit 2."""
    import sys

    from models.errors import ModelError

    try:
        code = main()
    except (ToolkitError, ModelError, ValueError) as error:  # bad input: one line, no traceback
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    raise SystemExit(code)
