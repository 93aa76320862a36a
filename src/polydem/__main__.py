import sys

from polydem.cli import main

sys.exit(main())
