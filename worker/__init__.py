"""Celery workers that run fluidcore jobs. Imports `service` (the core), never `api`."""
