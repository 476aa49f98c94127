"""``python -m estimator_service train|track|serve ...`` (see :mod:`estimator_service.cli`);
options alone (``python -m estimator_service --models DIR``) mean ``serve``."""

import sys

from estimator_service.cli import main

argv = sys.argv[1:]
raise SystemExit(
    main(
        ["serve", *argv]
        if argv and argv[0].startswith("--") and argv[0] not in ("--version", "--help")
        else argv
    )
)
