"""
How the stereo_manip graph is configured when its nodes run on several machines.

One place for the multi-host settings, used by the launch files (``multihost:=true``), by
:mod:`stereo_manip_bringup.multihost` (the test and the benchmark of the split) and printed by
``python -m stereo_manip_bringup.deployment`` for a shell:

* ``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET``: find the other machines by multicast;
* ``FASTRTPS_DEFAULT_PROFILES_FILE``: the shipped Fast DDS profile
  ``config/fastdds_multihost.xml`` (UDP datagrams of at most one Ethernet frame, 4 MB socket
  receive buffers; the reasons are in the file).

No rclpy; only the installed share directory (or the source tree) is looked up.
"""

from __future__ import annotations

from pathlib import Path
import shlex
import sys
from typing import Dict, Optional, Sequence

__all__ = ['MULTIHOST_PROFILE_FILE', 'multihost_profile_path', 'multihost_environment',
           'RECEIVE_BUFFER_BYTES', 'main']

MULTIHOST_PROFILE_FILE = 'fastdds_multihost.xml'
RECEIVE_BUFFER_BYTES = 4194304      # the profile's receiveBufferSize; net.core.rmem_max needed


def multihost_profile_path() -> Path:
    """
    Find the shipped Fast DDS profile: the installed share directory's, else the source tree's.

    :raises FileNotFoundError: neither exists (a broken install).
    """
    candidates = []
    try:
        from ament_index_python.packages import get_package_share_directory, \
            PackageNotFoundError
        try:
            candidates.append(Path(get_package_share_directory('stereo_manip_bringup'))
                              / 'config' / MULTIHOST_PROFILE_FILE)
        except PackageNotFoundError:
            pass
    except ImportError:
        pass
    candidates.append(Path(__file__).resolve().parents[1] / 'config' / MULTIHOST_PROFILE_FILE)
    for path in candidates:
        if path.is_file():
            return path
    raise FileNotFoundError(f'{MULTIHOST_PROFILE_FILE} not found (looked in '
                            f'{", ".join(str(p) for p in candidates)}); rebuild the workspace')


def multihost_environment(domain_id: Optional[int] = None) -> Dict[str, str]:
    """
    Environment variables every participant of a multi-host cell gets.

    :param domain_id: also set ``ROS_DOMAIN_ID`` (one id per cell, the same on every machine).
    """
    env = {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET',
           'FASTRTPS_DEFAULT_PROFILES_FILE': str(multihost_profile_path())}
    if domain_id is not None:
        env['ROS_DOMAIN_ID'] = str(int(domain_id))
    return env


def main(argv: Optional[Sequence[str]] = None) -> int:
    """
    Print the ``export`` lines of :func:`multihost_environment` for a shell.

    Use: ``eval "$(python -m stereo_manip_bringup.deployment)"``.
    """
    import argparse
    parser = argparse.ArgumentParser(prog='python -m stereo_manip_bringup.deployment',
                                     description='print the multi-host environment as '
                                                 'export lines')
    parser.add_argument('--domain-id', type=int, default=None, help='also export ROS_DOMAIN_ID')
    opts = parser.parse_args(argv)
    for key, value in multihost_environment(opts.domain_id).items():
        print(f'export {key}={shlex.quote(value)}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
