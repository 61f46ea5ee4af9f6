"""The service core shared by `api` (which queues jobs) and `worker` (which runs them).

Settings, the database and its tables, object storage, the job types with their parameter
models, the Celery app and the queue live here, so that neither side imports the other:
`api` never loads the worker's runners (nor torch through them), and `worker` never loads
FastAPI routes. Nothing here imports torch.
"""
