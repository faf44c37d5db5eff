"""The jobs table as the source of truth for background work: status, progress, attempts, results."""

from services.jobs.tracker import JobTracker, job_state

__all__ = ["JobTracker", "job_state"]
