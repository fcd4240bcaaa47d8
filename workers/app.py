"""Module-level queue for Huey's own consumer: ``huey_consumer workers.app.huey``.

Importing this module reads the ``LOOPNET_*`` settings and opens the queue storage; the API and
``loopnet worker`` build their queue with :class:`workers.queue.Queue` instead.
"""

from service.config import Settings
from workers.queue import Queue

queue = Queue(Settings())
huey = queue.huey
