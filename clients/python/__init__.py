"""articast Python client: subscribe to a session and receive typed frames.

Needs only ``websockets`` and ``pydantic`` (the wire schema is ``articast.service.protocol``, which
imports nothing else): no OpenCV, FastAPI or tracker. See docs/CLIENTS.md.
"""

from articast.client.client import Client, ClientClosed, ClientError, subscribe_sync

__all__ = ["Client", "ClientClosed", "ClientError", "subscribe_sync"]
