import sys

from vo_runtime.cli import main

sys.exit(main())
