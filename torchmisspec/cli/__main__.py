"""``python -m torchmisspec.cli``: the command line."""

from . import main

raise SystemExit(main())
