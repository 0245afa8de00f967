import sys

from magail_sumo.cli.main import main

sys.exit(main())
