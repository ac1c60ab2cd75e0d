"""Fan-out of reconstructed frames to stream clients, below the API.

``hub`` holds the clients' bounded queues (``Hub``, ``Subscriber``) and
encodes each frame at most once per (fields, encoding); ``encoding`` is the
frame's wire shapes (JSON and binary stream messages, the replay export line)
and their field and flag tables. Nothing here knows HTTP: the service
publishes into a ``Hub`` and the API only adds and removes subscribers.
"""
