"""``python -m vo_runtime``: the VO command; ``python -m vo_runtime verify ARTEFACT`` checks an artefact's runtime."""
import sys

if sys.argv[1:2] == ["verify"]:
    from vo_runtime.verify import main as verify_main

    sys.exit(verify_main(sys.argv[2:]))

from vo_runtime.cli import main

sys.exit(main())
