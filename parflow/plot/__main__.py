"""python -m parflow.plot FILE [FILE ...] [--out DIR] [--format png|pdf|svg] [--only NAME]"""
import sys

from . import main

sys.exit(main())
