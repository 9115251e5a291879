"""A plugin module that ends the process on import (tests/test_hostile_round4.py)."""
import sys

sys.exit(3)
