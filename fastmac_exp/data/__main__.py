"""`python -m fastmac_exp.data ...`: the same as `fastmac-exp data ...`."""

import sys

from fastmac_exp.data.cli import main

sys.exit(main(sys.argv[1:]))
