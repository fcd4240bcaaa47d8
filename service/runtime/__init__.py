"""The process plumbing on top of the use cases: a LoopNet process's start-up and shutdown
(:class:`Runtime`), the job queue and its wire format, the worker, and job recovery."""

from service.runtime.process import Runtime

__all__ = ["Runtime"]
