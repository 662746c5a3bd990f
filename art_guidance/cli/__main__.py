"""`python -m art_guidance.cli` = `art-guidance`."""
import sys

from art_guidance.cli import main

sys.exit(main())
