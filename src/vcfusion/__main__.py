import sys

from vcfusion.commands import main

sys.exit(main())
