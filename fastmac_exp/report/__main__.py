import sys

from fastmac_exp.report.tables import main

sys.exit(main())
