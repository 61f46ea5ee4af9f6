"""One router per resource: scenes, jobs, artifacts, health."""
