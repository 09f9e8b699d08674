"""``python -m occkit ...``, which is how ``torchrun --nproc-per-node N -m occkit train ...`` starts occkit."""

import sys

from occkit.cli import main

sys.exit(main())
