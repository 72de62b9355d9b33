"""articast Python client: subscribe to a session and receive typed frames.

Needs only ``websockets`` and ``pydantic``: no numpy, OpenCV, FastAPI or tracker. The wire schema
lives here (:mod:`articast.client.protocol`) and the server imports it from here, so both sides
share one definition and the client never imports the server. It installs on its own as the
``articast-client`` distribution (``pip install clients/python``). See docs/CLIENTS.md.
"""

from articast.client.client import (
    Client,
    ClientClosed,
    ClientError,
    ClientRefused,
    subscribe_sync,
)

__all__ = ["Client", "ClientClosed", "ClientError", "ClientRefused", "subscribe_sync"]
