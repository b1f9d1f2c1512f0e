import sys

from fdnet.cli import main

sys.exit(main())
