"""``python -m estimator_service --models DIR``: run the zenoh estimator service."""

from estimator_service.service.server import main

raise SystemExit(main())
