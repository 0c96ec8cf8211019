"""
Several simulated machines on one Linux host: network namespaces on a virtual Ethernet LAN.

Each *host* is a network namespace with its own loopback and one Ethernet interface ``eth0``
(a TAP device). A small switch process (:func:`relay_main`, started by :class:`VirtualLan`)
holds the other end of every TAP and forwards Ethernet frames between the hosts with MAC
learning, like a switch, adding the one-way ``delay`` and dropping a ``loss`` fraction of the
frames each host sends (what ``tc netem`` does; ``sch_netem`` is not built into every kernel,
so the delay and loss live here). The link *rate* is the kernel's: a ``tc tbf`` qdisc on each
host's ``eth0`` egress, like a NIC of that speed.

Nothing touches the machine's own network: the TAPs are created inside namespaces this module
created, with addresses of a private subnet that exists only there; :meth:`VirtualLan.destroy`
stops the switch (the TAPs vanish with it) and deletes exactly its own namespaces, by name. The
switch also exits by itself when its parent process dies or after ``max_seconds``.

Pure subprocess/os (``ip``, ``tc``, ``/dev/net/tun``); needs root. No rclpy: processes are
started inside a host with :meth:`VirtualLan.command` (``ip netns exec``), so a DDS participant
in one host reaches the others only over this LAN, as on separate machines.

Example::

    with VirtualLan(['camera', 'perception'], rate_bit_s=100e6, delay_s=0.5e-3,
                    loss=0.001) as lan:
        proc = subprocess.Popen(lan.command('camera', ['python3', 'talker.py']))
        ...
        print(lan.switch_stats())
"""

from __future__ import annotations

import argparse
import collections
import ctypes
import fcntl
import ipaddress
import json
import os
from pathlib import Path
import random
import re
import select
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from typing import Any, Dict, List, Optional, Sequence
import uuid

__all__ = ['VirtualLan', 'NetnsError', 'netns_unavailable_reason', 'list_namespaces',
           'relay_main']

_TUNSETIFF = 0x400454ca
_IFF_TAP = 0x0002
_IFF_NO_PI = 0x1000
_CLONE_NEWNET = 0x40000000


class NetnsError(RuntimeError):
    """An ``ip``/``tc`` command or the switch failed; the message says which and why."""


def _run(cmd: Sequence[str], check: bool = True, timeout: float = 20.0) -> str:
    proc = subprocess.run(list(cmd), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True, timeout=timeout)
    if check and proc.returncode != 0:
        raise NetnsError(f'`{" ".join(cmd)}` failed ({proc.returncode}): {proc.stdout.strip()}')
    return proc.stdout


def list_namespaces() -> List[str]:
    """Names of the network namespaces that exist now (``ip netns list``)."""
    out = _run(['ip', 'netns', 'list'], check=False)
    return [line.split()[0] for line in out.splitlines() if line.strip()]


def netns_unavailable_reason() -> Optional[str]:
    """
    Why simulated hosts cannot be made here, or None when they can.

    Checks root, ``ip``/``tc`` and ``/dev/net/tun``, then builds (and deletes) a one-host LAN
    with a ``tbf`` qdisc, because containers often refuse a part of it.
    """
    if not sys.platform.startswith('linux'):
        return 'network namespaces need Linux'
    if os.geteuid() != 0:
        return 'network namespaces need root (CAP_NET_ADMIN, CAP_SYS_ADMIN)'
    for tool in ('ip', 'tc'):
        if shutil.which(tool) is None:
            return f'the `{tool}` tool (iproute2) is not installed'
    if not os.path.exists('/dev/net/tun'):
        return '/dev/net/tun is missing (TAP devices unavailable)'
    lan = VirtualLan(['probe'], rate_bit_s=1e9, tag=f'p{uuid.uuid4().hex[:5]}')
    try:
        lan.create()
    except (NetnsError, OSError, subprocess.SubprocessError) as exc:
        return f'cannot build a simulated LAN here: {exc}'
    finally:
        lan.destroy()
    return None


class VirtualLan:
    """
    Hosts (network namespaces) on one simulated Ethernet segment, every link shaped alike.

    :param hosts: host names (letters, digits, ``_``); host ``k`` gets address ``.k+1``.
    :param rate_bit_s: each host's link rate [bit/s] (kernel ``tbf`` on its egress); None =
        unlimited.
    :param delay_s: one-way delay [s] added to every frame a host sends (the switch).
    :param loss: fraction of the frames a host sends that the switch drops at random.
    :param subnet: IPv4 subnet in 10.0.0.0/8 or 169.254.0.0/16; exists only in these hosts.
    :param tag: unique part of the namespace names ``sm<tag>_<host>`` (default random).
    :param mtu: MTU of every link [bytes] (1500, an ordinary Ethernet).
    :param queue_s: tbf queue length as time at ``rate_bit_s`` (a switch buffer) [s].
    :param seed: seed of the switch's loss draws.
    :param max_seconds: the switch exits by itself after this long [s].
    """

    def __init__(self, hosts: Sequence[str], rate_bit_s: Optional[float] = None,
                 delay_s: float = 0.0, loss: float = 0.0, subnet: str = '10.217.0.0/24',
                 tag: Optional[str] = None, mtu: int = 1500, queue_s: float = 0.1,
                 seed: int = 0, max_seconds: float = 3600.0) -> None:
        if not hosts or len(set(hosts)) != len(hosts):
            raise ValueError(f'hosts must be distinct and non-empty, got {list(hosts)}')
        for h in hosts:
            if not h.replace('_', '').isalnum():
                raise ValueError(f'host name {h!r}: use letters, digits and _ only')
        net = ipaddress.ip_network(subnet)
        if not (net.version == 4 and (net.subnet_of(ipaddress.ip_network('10.0.0.0/8'))
                                      or net.subnet_of(ipaddress.ip_network('169.254.0.0/16')))):
            raise ValueError(f'subnet {subnet} must lie in 10.0.0.0/8 or 169.254.0.0/16')
        if net.num_addresses < len(hosts) + 2:
            raise ValueError(f'subnet {subnet} is too small for {len(hosts)} hosts')
        if not 0.0 <= loss < 1.0:
            raise ValueError(f'loss must be in [0, 1), got {loss}')
        if delay_s < 0 or (rate_bit_s is not None and not rate_bit_s > 0):
            raise ValueError(f'delay must be >= 0 and rate > 0, got {delay_s}, {rate_bit_s}')
        self.tag = tag or uuid.uuid4().hex[:6]
        self.hosts: List[str] = list(hosts)
        self.subnet = net
        self.mtu = int(mtu)
        self.rate_bit_s = rate_bit_s
        self.delay_s = float(delay_s)
        self.loss = float(loss)
        self.queue_s = float(queue_s)
        self.seed = int(seed)
        self.max_seconds = float(max_seconds)
        self.namespaces: Dict[str, str] = {h: f'sm{self.tag}_{h}' for h in self.hosts}
        self.addresses: Dict[str, str] = {
            h: str(net.network_address + k + 1) for k, h in enumerate(self.hosts)}
        self._created: List[str] = []
        self._switch: Optional[subprocess.Popen] = None
        self._stats_path = Path(tempfile.gettempdir()) / f'sm{self.tag}_switch.json'
        self._final_stats: Optional[Dict[str, Any]] = None

    # --- life cycle ------------------------------------------------------------------------

    def create(self) -> 'VirtualLan':
        """
        Create the host namespaces, the switch, addresses, route and rate limit.

        Create the host namespaces, start the switch (which makes each host's ``eth0``),
        then set addresses, multicast route and the rate limit.

        On failure everything created so far is removed before the error propagates.
        """
        try:
            for host in self.hosts:
                ns = self.namespaces[host]
                _run(['ip', 'netns', 'add', ns])
                self._created.append(ns)
                _run(['ip', '-n', ns, 'link', 'set', 'lo', 'up'])
            cmd = [sys.executable, '-m', 'stereo_manip_tools.netns', '--stats',
                   str(self._stats_path), '--delay', repr(self.delay_s), '--loss',
                   repr(self.loss), '--seed', str(self.seed), '--max-seconds',
                   repr(self.max_seconds), '--mtu', str(self.mtu),
                   *[self.namespaces[h] for h in self.hosts]]
            env = dict(os.environ)
            env['PYTHONPATH'] = os.pathsep.join(
                [str(Path(__file__).resolve().parent.parent)]
                + ([env['PYTHONPATH']] if env.get('PYTHONPATH') else []))
            self._switch = subprocess.Popen(cmd, stdout=subprocess.PIPE,
                                            stderr=subprocess.STDOUT, text=True, env=env)
            line = self._switch.stdout.readline() if self._switch.stdout else ''
            if line.strip() != 'ready':
                rest = self._switch.stdout.read() if self._switch.stdout else ''
                raise NetnsError(f'the switch did not start: {line}{rest}')
            for host in self.hosts:
                hn = ['ip', '-n', self.namespaces[host]]
                _run(hn + ['link', 'set', 'eth0', 'mtu', str(self.mtu), 'txqueuelen', '10000'])
                _run(hn + ['addr', 'add', f'{self.addresses[host]}/{self.subnet.prefixlen}',
                           'dev', 'eth0'])
                _run(hn + ['link', 'set', 'eth0', 'up', 'multicast', 'on'])
                # DDS discovery multicasts to 239.255.0.1: route multicast onto the LAN
                _run(hn + ['route', 'add', '224.0.0.0/4', 'dev', 'eth0'])
                if self.rate_bit_s is not None:
                    rate = float(self.rate_bit_s)
                    burst = max(int(rate / 8 / 1000), 4 * self.mtu)    # 1 ms of traffic
                    limit = int(rate / 8 * self.queue_s) + burst
                    _run(['ip', 'netns', 'exec', self.namespaces[host], 'tc', 'qdisc', 'add',
                          'dev', 'eth0', 'root', 'tbf', 'rate', f'{int(rate)}bit', 'burst',
                          str(burst), 'limit', str(limit)])
            self._add_static_neighbours()
        except BaseException:
            self.destroy()
            raise
        return self

    def _add_static_neighbours(self) -> None:
        """
        Give every host a permanent ARP entry for every other host.

        The switch drops a ``loss`` fraction of *all* frames, ARP included; a lost ARP request
        makes the kernel wait ``retrans_time`` (1 s) before asking again and hold the unicast
        datagrams meanwhile, a one-second stall at start that no link of the simulated kind
        adds and that would dominate short measurements. Static entries leave only the delay
        and loss of the data frames themselves.
        """
        macs = {}
        for host in self.hosts:
            link = _run(['ip', '-n', self.namespaces[host], '-o', 'link', 'show', 'eth0'])
            match = re.search(r'link/ether ([0-9a-f:]{17})', link)
            if match is None:
                raise NetnsError(f'no MAC address on {self.namespaces[host]} eth0: {link}')
            macs[host] = match.group(1)
        for host in self.hosts:
            for other in self.hosts:
                if other != host:
                    _run(['ip', '-n', self.namespaces[host], 'neigh', 'replace',
                          self.addresses[other], 'lladdr', macs[other], 'dev', 'eth0',
                          'nud', 'permanent'])

    def destroy(self) -> List[str]:
        """
        Stop the switch and delete the namespaces this object created (by name).

        Safe to call twice. Returns the names that could not be deleted (normally none).
        """
        if self._switch is not None:
            if self._switch.poll() is None:
                self._switch.send_signal(signal.SIGTERM)
                try:
                    self._switch.wait(10)
                except subprocess.TimeoutExpired:
                    self._switch.kill()
                    self._switch.wait(5)
            if self._switch.stdout:
                self._switch.stdout.close()
            self._switch = None
            try:
                self._final_stats = json.loads(self._stats_path.read_text())
                self._stats_path.unlink()
            except (OSError, ValueError):
                pass
        failed = []
        for name in reversed(self._created):
            out = subprocess.run(['ip', 'netns', 'delete', name], stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, text=True, timeout=20)
            if out.returncode != 0 and name in list_namespaces():
                failed.append(name)
        self._created = [n for n in self._created if n in failed]
        return failed

    def __enter__(self) -> 'VirtualLan':
        return self.create()

    def __exit__(self, *exc: object) -> None:
        self.destroy()

    # --- use -------------------------------------------------------------------------------

    def command(self, host: str, argv: Sequence[str]) -> List[str]:
        """
        ``argv`` prefixed to run inside ``host``.

        ``argv`` prefixed to run inside ``host`` (``ip netns exec`` execs ``argv``, so the
        process id is the command's own and signals reach it directly).
        """
        return ['ip', 'netns', 'exec', self.namespaces[host], *argv]

    def counters(self, host: str) -> Dict[str, int]:
        """``host``'s eth0 counters from sysfs: rx/tx bytes and packets, tx drops."""
        out = _run(['ip', 'netns', 'exec', self.namespaces[host], 'sh', '-c',
                    'cd /sys/class/net/eth0/statistics && '
                    'echo $(cat rx_bytes tx_bytes rx_packets tx_packets tx_dropped)'])
        rx_b, tx_b, rx_p, tx_p, tx_d = (int(v) for v in out.split())
        return {'rx_bytes': rx_b, 'tx_bytes': tx_b, 'rx_packets': rx_p, 'tx_packets': tx_p,
                'tx_dropped': tx_d}

    def ip_stats(self, host: str) -> Dict[str, int]:
        """
        ``host``'s IP reassembly and UDP counters and the memory its incomplete fragments hold now.

        From ``/proc/net/snmp``: ``Reasm*`` (ReasmReqds, ReasmOKs, ReasmFails) and ``Udp*``
        (e.g. ``UdpRcvbufErrors``: datagrams dropped because a socket's receive buffer was
        full; ``UdpSndbufErrors``); from ``/proc/net/sockstat``: ``frag_memory_bytes``.
        """
        out = _run(['ip', 'netns', 'exec', self.namespaces[host], 'cat', '/proc/net/snmp',
                    '/proc/net/sockstat'])
        stats: Dict[str, int] = {}
        for proto, keep in (('Ip:', 'Reasm'), ('Udp:', '')):
            rows = [line.split()[1:] for line in out.splitlines() if line.startswith(proto)]
            if len(rows) >= 2:
                prefix = '' if keep else 'Udp'
                stats.update({prefix + k: int(v) for k, v in zip(rows[0], rows[1])
                              if k.startswith(keep)})
        for line in out.splitlines():
            if line.startswith('FRAG:'):
                f = line.split()
                stats['frag_memory_bytes'] = int(f[f.index('memory') + 1])
        return stats

    def qdisc_stats(self, host: str) -> str:
        """``tc -s qdisc`` of ``host``'s eth0 (bytes sent, drops and overlimits of the tbf)."""
        return _run(['ip', 'netns', 'exec', self.namespaces[host], 'tc', '-s', 'qdisc', 'show',
                     'dev', 'eth0'])

    def switch_stats(self) -> Optional[Dict[str, Any]]:
        """
        Return the switch's figures.

        The switch's figures (per host: frames/bytes sent, dropped by ``loss``; delivery
        lateness beyond ``delay_s`` p50/p90/max; its CPU time): live while it runs (it
        rewrites them every second), final after :meth:`destroy`.
        """
        if self._final_stats is not None and self._switch is None:
            return self._final_stats
        try:
            return json.loads(self._stats_path.read_text())
        except (OSError, ValueError):
            return None

    def switch_running(self) -> bool:
        """Tell whether the switch process runs."""
        return self._switch is not None and self._switch.poll() is None


# --- the switch process -------------------------------------------------------------------

def _open_taps(namespaces: Sequence[str]) -> List[int]:
    """Create a TAP ``eth0`` in each namespace (entering it with setns) and return the fds."""
    libc = ctypes.CDLL(None, use_errno=True)
    own = os.open('/proc/self/ns/net', os.O_RDONLY)
    fds = []
    try:
        for ns in namespaces:
            nsfd = os.open(f'/var/run/netns/{ns}', os.O_RDONLY)
            try:
                if libc.setns(nsfd, _CLONE_NEWNET) != 0:
                    raise OSError(ctypes.get_errno(), f'setns into {ns} failed')
                fd = os.open('/dev/net/tun', os.O_RDWR | os.O_NONBLOCK)
                fcntl.ioctl(fd, _TUNSETIFF, struct.pack('16sH', b'eth0', _IFF_TAP | _IFF_NO_PI))
                fds.append(fd)
            finally:
                os.close(nsfd)
    finally:
        if libc.setns(own, _CLONE_NEWNET) != 0:
            raise OSError(ctypes.get_errno(), 'setns back to the own namespace failed')
        os.close(own)
    return fds


def _percentiles(values: List[float]) -> Dict[str, float]:
    if not values:
        return {'n': 0}
    v = sorted(values)

    def q(p: float) -> float:
        return v[min(len(v) - 1, int(round(p * (len(v) - 1))))]
    return {'n': len(v), 'p50': q(0.5), 'p90': q(0.9), 'p99': q(0.99), 'max': v[-1]}


def relay_main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the switch: forward frames between the hosts' TAPs with delay and loss (see module)."""
    parser = argparse.ArgumentParser(prog='python -m stereo_manip_tools.netns',
                                     description='simulated Ethernet switch between TAPs')
    parser.add_argument('namespaces', nargs='+')
    parser.add_argument('--delay', type=float, default=0.0, help='one-way delay [s]')
    parser.add_argument('--loss', type=float, default=0.0, help='frame loss fraction')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--max-seconds', type=float, default=3600.0)
    parser.add_argument('--mtu', type=int, default=1500)
    parser.add_argument('--stats', required=True, help='JSON file for the figures')
    opts = parser.parse_args(argv)
    # A real network does not wait for the hosts' CPUs: run the switch at a (low) real-time
    # priority so its forwarding is not delayed behind the simulated hosts' processes. It
    # blocks in select() between frames; the kernel's RT throttling bounds it anyway.
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except (OSError, AttributeError):
        try:
            os.nice(-10)
        except OSError:
            pass
    fds = _open_taps(opts.namespaces)
    port_of_fd = {fd: k for k, fd in enumerate(fds)}
    parent = os.getppid()
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    rng = random.Random(opts.seed)
    n = len(fds)
    sent_frames, sent_bytes, lost_frames, lost_bytes = [0] * n, [0] * n, [0] * n, [0] * n
    delivered_frames, delivered_bytes, write_errors = [0] * n, [0] * n, [0] * n
    lateness: List[float] = []
    macs: Dict[bytes, int] = {}
    queue: collections.deque = collections.deque()   # (due, src port, frame): FIFO, fixed delay
    t_start = time.monotonic()
    t_stats = t_start
    bufsize = opts.mtu + 64
    cpu0 = os.times()

    def write_stats() -> None:
        cpu = os.times()
        stats = {
            'hosts': {ns: {'sent_frames': sent_frames[k], 'sent_bytes': sent_bytes[k],
                           'lost_frames': lost_frames[k], 'lost_bytes': lost_bytes[k],
                           'delivered_frames': delivered_frames[k],
                           'delivered_bytes': delivered_bytes[k],
                           'write_errors': write_errors[k]}
                      for k, ns in enumerate(opts.namespaces)},
            'delay_s': opts.delay, 'loss': opts.loss,
            'lateness_s': _percentiles(lateness[-200000:]),
            'seconds': time.monotonic() - t_start,
            'cpu_seconds': (cpu.user - cpu0.user) + (cpu.system - cpu0.system),
        }
        tmp = opts.stats + '.tmp'
        with open(tmp, 'w') as f:
            json.dump(stats, f)
        os.replace(tmp, opts.stats)

    print('ready', flush=True)
    while not stop:
        now = time.monotonic()
        if now - t_start > opts.max_seconds or os.getppid() != parent:
            break
        timeout = 0.2
        if queue:
            timeout = min(timeout, max(0.0, queue[0][0] - now))
        try:
            readable, _, _ = select.select(fds, [], [], timeout)
        except InterruptedError:
            continue
        now = time.monotonic()
        for fd in readable:
            k = port_of_fd[fd]
            for _ in range(512):
                try:
                    frame = os.read(fd, bufsize)
                except BlockingIOError:
                    break
                except OSError:
                    break
                if len(frame) < 14:
                    continue
                sent_frames[k] += 1
                sent_bytes[k] += len(frame)
                if opts.loss > 0 and rng.random() < opts.loss:
                    lost_frames[k] += 1
                    lost_bytes[k] += len(frame)
                    continue
                src = frame[6:12]
                if not src[0] & 1:
                    macs[src] = k
                queue.append((now + opts.delay, k, frame))
        now = time.monotonic()
        while queue and queue[0][0] <= now:
            due, k, frame = queue.popleft()
            dst = frame[0:6]
            port = None if dst[0] & 1 else macs.get(dst)
            targets = [port] if port is not None else [p for p in range(n) if p != k]
            for p in targets:
                if p == k:
                    continue
                try:
                    os.write(fds[p], frame)
                    delivered_frames[p] += 1
                    delivered_bytes[p] += len(frame)
                except OSError:
                    write_errors[p] += 1
            lateness.append(now - due)
        if len(lateness) > 400000:
            del lateness[:200000]
        if now - t_stats > 1.0:
            t_stats = now
            write_stats()
    write_stats()
    for fd in fds:
        os.close(fd)
    return 0


if __name__ == '__main__':
    sys.exit(relay_main())
