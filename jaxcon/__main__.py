import sys

from jaxcon.bench.cli import main

sys.exit(main())
