import sys

from vcfusion.cli import main

sys.exit(main())
