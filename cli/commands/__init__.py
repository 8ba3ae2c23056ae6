"""One module per ``facecast`` sub-command; each defines ``register(subparsers)``.

Modules import nothing heavy at import time: the work is imported inside ``run``.
Modules named ``_…`` are not commands but helpers several commands share.
"""
