"""The Ray cluster the distributed commands run on (``render --workers``,
``fit --workers``, ``sweep``): a running one at an address, or a local one of
this machine's processes."""
from __future__ import annotations

import os

from mi_tetvr.extras import needs


def connect(workers, address=None):
    """Join the Ray cluster at ``address`` (default ``RAY_ADDRESS``), or start a
    local one of this machine's cores (at least ``workers`` slots); True
    where it was started here (the caller shuts it down). A clear
    ``ConnectionError`` where no cluster answers."""
    with needs("cluster", "work over Ray workers"):
        import ray
    if ray.is_initialized():
        return False
    address = address or os.environ.get("RAY_ADDRESS")
    try:
        if address:
            _reachable(address)
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=max(os.cpu_count() or 1, int(workers)), include_dashboard=False,
                     log_to_driver=False)
    except ConnectionError as e:
        raise ConnectionError(f"no Ray cluster answers at {address!r} ({e}); start one with "
                              f"`ray start --head`, or leave the address out for a local "
                              f"one") from None
    return True


def _reachable(address, timeout=5.0):
    """A ``ConnectionError`` now where nothing listens at a ``HOST:PORT``
    address (Ray itself would retry for minutes); other forms (``auto``,
    ``ray://...``) are left to Ray."""
    import socket
    host, sep, port = str(address).rpartition(":")
    if not sep or not port.isdigit() or "/" in host:
        return
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except OSError as e:
        raise ConnectionError(f"nothing answers at {address} ({e})") from None
