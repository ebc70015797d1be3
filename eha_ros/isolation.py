"""Isolated ROS 2 environments: a reserved ``ROS_DOMAIN_ID`` and a temporary ``ROS_LOG_DIR``.

Anything that starts ROS 2 nodes next to other runs on the same machine (tests, the campaign,
bench scripts, ``eha-graph --isolated``) takes its environment from :func:`ros_environment`:
its own ``ROS_DOMAIN_ID`` (so simultaneous runs never see each other's topics) and a temporary
``ROS_LOG_DIR`` (so nothing is written to ``~/.ros/log``).
"""

from contextlib import contextmanager
import errno
import fcntl
import itertools
import os
from pathlib import Path
import shutil
import tempfile
from typing import Dict, Iterator, Optional

__all__ = ['DOMAIN_IDS', 'RMW_IMPLEMENTATION', 'DomainIdLease', 'allocate_domain_id',
           'ros_environment']

#: ROS domain IDs handed out to isolated runs. Up to 101 the DDS ports (7400 + 250 * id +
#: offsets) stay below Linux's ephemeral port range (32768 and up); 0 is left to whatever runs
#: by default.
DOMAIN_IDS = range(1, 102)

#: RMW implementation isolated runs use.
RMW_IMPLEMENTATION = 'rmw_fastrtps_cpp'

_counter = itertools.count()


class DomainIdLease:
    """A ROS domain ID reserved for this process until :meth:`release` (or process exit).

    The reservation is an exclusive ``flock`` on ``<tmp>/eha_ros-ros-domain-ids/<id>.lock``:
    other processes using this class skip IDs that are held, and the operating system drops
    the lock if the process dies, so no stale reservation survives a crash.
    """

    def __init__(self, domain_id: int, handle: int):
        self.domain_id = domain_id
        self._handle: Optional[int] = handle

    def release(self) -> None:
        """Give the domain ID back."""
        if self._handle is not None:
            fcntl.flock(self._handle, fcntl.LOCK_UN)
            os.close(self._handle)
            self._handle = None


def allocate_domain_id(lock_dir: Optional[Path] = None) -> DomainIdLease:
    """Reserve a ROS domain ID in :data:`DOMAIN_IDS` that no other test process holds.

    The search starts at a point derived from the process ID and a per-process counter, so
    concurrent processes usually get different IDs at the first try.

    Parameters
    ----------
    lock_dir : pathlib.Path, optional
        Folder of the lock files; default ``<tempdir>/eha_ros-ros-domain-ids``.

    Raises
    ------
    RuntimeError
        If every ID in :data:`DOMAIN_IDS` is held.
    """
    lock_dir = Path(lock_dir or Path(tempfile.gettempdir()) / 'eha_ros-ros-domain-ids')
    lock_dir.mkdir(parents=True, exist_ok=True)
    ids = list(DOMAIN_IDS)
    start = (os.getpid() * 7919 + next(_counter) * 37) % len(ids)
    for offset in range(len(ids)):
        domain_id = ids[(start + offset) % len(ids)]
        handle = os.open(lock_dir / f'{domain_id}.lock', os.O_CREAT | os.O_RDWR, 0o666)
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(handle)
            if exc.errno in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                continue
            raise
        return DomainIdLease(domain_id, handle)
    raise RuntimeError(f'all ROS domain IDs {ids[0]}..{ids[-1]} are in use by other tests')


@contextmanager
def ros_environment(base: Optional[Dict[str, str]] = None) -> Iterator[Dict[str, str]]:
    """Yield an environment for ROS 2 processes isolated from every other test run.

    Parameters
    ----------
    base : dict, optional
        Environment to start from; default a copy of ``os.environ`` (which carries the
        ``LD_LIBRARY_PATH`` the ROS wheels need).

    Yields
    ------
    dict
        ``base`` plus a reserved ``ROS_DOMAIN_ID``, a fresh temporary ``ROS_LOG_DIR`` (removed
        afterwards), ``RMW_IMPLEMENTATION=rmw_fastrtps_cpp``, discovery limited to this machine
        and type/range checks on message field assignment (``ROS_PYTHON_CHECK_FIELDS=1``).
    """
    env = dict(os.environ if base is None else base)
    lease = allocate_domain_id()
    log_dir = tempfile.mkdtemp(prefix=f'eha_ros-ros-log-{lease.domain_id}-')
    env.update({
        'ROS_DOMAIN_ID': str(lease.domain_id),
        'ROS_LOG_DIR': log_dir,
        'RMW_IMPLEMENTATION': RMW_IMPLEMENTATION,
        'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
        'ROS_PYTHON_CHECK_FIELDS': '1',
    })
    env.pop('ROS_STATIC_PEERS', None)
    try:
        yield env
    finally:
        lease.release()
        shutil.rmtree(log_dir, ignore_errors=True)
