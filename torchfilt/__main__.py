"""``python -m torchfilt`` runs the command line."""

from torchfilt.cli import main

raise SystemExit(main())
