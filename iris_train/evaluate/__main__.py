"""``python -m iris_train.evaluate``: the ``iris-eval`` command."""
import sys

from .cli import main

sys.exit(main())
