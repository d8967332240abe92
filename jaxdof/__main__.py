"""`python -m jaxdof ...`: the same as the `jaxdof` script."""

import sys

from ._cli import main


if __name__ == "__main__":
    sys.exit(main())
