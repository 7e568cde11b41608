"""``python -m jaxvox``: the command line (see `jaxvox.cli`)."""

from jaxvox.cli import main

raise SystemExit(main())
