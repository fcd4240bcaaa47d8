"""LoopNet: a place-recognition (loop-closure) service for robots and robot fleets."""

__version__ = "0.1.0"
