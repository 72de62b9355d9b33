"""The browser avatar: static files served by the service at /avatar/ (service/avatar.py)."""
