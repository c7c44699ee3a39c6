import sys

from mono_map.cli import main

sys.exit(main())
