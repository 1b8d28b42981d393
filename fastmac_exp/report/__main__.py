import sys

from fastmac_exp.report.cli import main

sys.exit(main())
