"""Celery workers that run fluidcore jobs."""
