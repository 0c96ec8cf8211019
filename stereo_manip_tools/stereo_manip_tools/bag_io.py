"""
rosbag2 reading and writing on ``rosbags`` (no rosbag2 install needed), shared by every tool.

Bags are written in rosbag2 format (mcap storage by default, Jazzy's default; sqlite3 on
request), so ``ros2 bag play`` replays them on a real ROS install. Messages are kept as the CDR
bytes rclpy sends and receives, so nothing is (de)serialised twice. Types that the Jazzy type
store lacks (our ``stereo_manip_msgs``) are registered from the ``.msg`` files the installed
interface packages ship.
"""

from __future__ import annotations

from dataclasses import dataclass
import importlib
import os
from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple

__all__ = [
    'BagError',
    'get_message_class',
    'make_typestore',
    'BagMessage',
    'BagWriter',
    'read_bag',
    'salvage_mcap',
    'bag_summary',
]


class BagError(RuntimeError):
    """A bag or topic problem with a message meant for the user (no traceback needed)."""


def get_message_class(type_name: str) -> Any:
    """
    Python class of a ROS interface type such as ``sensor_msgs/msg/Image``.

    :raises BagError: malformed name or the interface package is not installed.
    """
    parts = type_name.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or not all(parts):
        raise BagError(f'malformed message type {type_name!r} (expected pkg/msg/Name)')
    pkg, kind, name = parts
    try:
        module = importlib.import_module(f'{pkg}.{kind}')
        return getattr(module, name)
    except (ImportError, AttributeError) as exc:
        raise BagError(f'unknown message type {type_name!r}: interface package {pkg!r} has no '
                       f'{kind} {name!r} installed') from exc


def _share_msg_files(package: str) -> List[Path]:
    from ament_index_python.packages import get_package_share_directory

    share = Path(get_package_share_directory(package))
    return sorted((share / 'msg').glob('*.msg'))


def make_typestore(extra_packages: Sequence[str] = ('stereo_manip_msgs',)) -> Any:
    """Make the ROS 2 Jazzy type store plus every message of ``extra_packages`` (share/*/msg)."""
    from rosbags.typesys import get_types_from_msg, get_typestore, Stores

    store = get_typestore(Stores.ROS2_JAZZY)
    for package in extra_packages:
        try:
            files = _share_msg_files(package)
        except Exception:  # noqa: BLE001 - package not built: its types are simply unknown
            continue
        types: Dict[str, Any] = {}
        for f in files:
            types.update(get_types_from_msg(f.read_text(), f'{package}/msg/{f.stem}'))
        store.register(types)
    return store


@dataclass
class BagMessage:
    """One message of a bag: topic, type name, receive time [ns], CDR bytes."""

    topic: str
    msgtype: str
    timestamp: int
    data: bytes


class BagWriter:
    """Write CDR messages to a new rosbag2 bag (``storage``: ``'mcap'`` or ``'sqlite3'``)."""

    def __init__(self, path: os.PathLike | str, storage: str = 'mcap',
                 typestore: Any = None) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugins = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
        if storage not in plugins:
            raise BagError(f'unknown storage {storage!r}; use mcap or sqlite3')
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f'output bag {self.path} already exists')
        self.typestore = typestore if typestore is not None else make_typestore()
        self._writer = Writer(self.path, version=9, storage_plugin=plugins[storage])
        self._writer.open()
        self._connections: Dict[str, Any] = {}
        self.counts: Dict[str, int] = {}

    def add_topic(self, topic: str, msgtype: str) -> None:
        """Declare a topic; raises BagError if the type is unknown to the type store."""
        if topic in self._connections:
            return
        if msgtype not in self.typestore.types:
            raise BagError(f'topic {topic}: type {msgtype!r} is unknown to the bag type store')
        self._connections[topic] = self._writer.add_connection(topic, msgtype,
                                                               typestore=self.typestore)
        self.counts[topic] = 0

    def write(self, topic: str, timestamp_ns: int, data: bytes) -> None:
        """Append one CDR-serialised message received at ``timestamp_ns``."""
        self._writer.write(self._connections[topic], int(timestamp_ns), bytes(data))
        self.counts[topic] += 1

    def flush(self) -> None:
        """
        Make everything written so far durable against the process being killed.

        Mcap closes the pending chunk (a complete, indexed record) and flushes the file; sqlite3
        commits. A bag cut off after a flush is readable up to it (see :func:`read_bag`).
        """
        storage = getattr(self._writer, 'storage', None)
        if storage is None:
            return
        if hasattr(storage, 'close_chunk'):                 # mcap
            if storage.chunk.bio.tell():
                storage.close_chunk()
            storage.bio.flush()
        elif hasattr(storage, 'conn'):                      # sqlite3
            storage.conn.commit()

    def close(self) -> None:
        """Finish the bag (writes metadata.yaml)."""
        self._writer.close()

    def __enter__(self) -> 'BagWriter':
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _read_string(buf: bytes, pos: int) -> Tuple[str, int]:
    n = int.from_bytes(buf[pos:pos + 4], 'little')
    return buf[pos + 4:pos + 4 + n].decode('utf-8', 'replace'), pos + 4 + n


def _mcap_records(buf: bytes, pos: int, end: int) -> Iterator[Tuple[int, bytes]]:
    """(opcode, content) of the complete records in ``buf[pos:end]``; stops at a cut one."""
    while pos + 9 <= end:
        op = buf[pos]
        length = int.from_bytes(buf[pos + 1:pos + 9], 'little')
        if pos + 9 + length > end:
            return
        yield op, buf[pos + 9:pos + 9 + length]
        pos += 9 + length


def salvage_mcap(path: os.PathLike | str) -> Iterator[BagMessage]:
    """
    Messages of an mcap file that was never closed (writer killed).

    Every complete, uncompressed chunk and top-level message record up to where the file was cut,
    in file order (the recorder writes in receive order).
    """
    buf = Path(path).read_bytes()
    if not buf.startswith(b'\x89MCAP'):
        raise BagError(f'{path} is not an mcap file')
    schemas: Dict[int, str] = {}
    channels: Dict[int, Tuple[str, str]] = {}

    def walk(records: Iterator[Tuple[int, bytes]]) -> Iterator[BagMessage]:
        for op, rec in records:
            if op == 0x03:                                          # schema
                sid = int.from_bytes(rec[:2], 'little')
                schemas[sid], _ = _read_string(rec, 2)
            elif op == 0x04:                                        # channel
                cid = int.from_bytes(rec[:2], 'little')
                sid = int.from_bytes(rec[2:4], 'little')
                topic, _ = _read_string(rec, 4)
                channels[cid] = (topic, schemas.get(sid, ''))
            elif op == 0x05 and len(rec) >= 22:                     # message
                cid = int.from_bytes(rec[:2], 'little')
                if cid in channels:
                    topic, msgtype = channels[cid]
                    yield BagMessage(topic, msgtype, int.from_bytes(rec[6:14], 'little'),
                                     bytes(rec[22:]))
            elif op == 0x06:                                        # chunk
                compression, pos = _read_string(rec, 28)
                size = int.from_bytes(rec[pos:pos + 8], 'little')
                if compression:          # our writer does not compress; skip such chunks
                    continue
                inner = rec[pos + 8:pos + 8 + size]
                yield from walk(_mcap_records(inner, 0, len(inner)))

    yield from walk(_mcap_records(buf, 8, len(buf)))


def _salvage_sqlite(path: Path) -> Iterator[BagMessage]:
    import sqlite3

    conn = sqlite3.connect(f'file:{path}?mode=ro', uri=True)
    try:
        rows = conn.execute('SELECT topics.name, topics.type, messages.timestamp, '
                            'messages.data FROM messages JOIN topics ON '
                            'messages.topic_id = topics.id ORDER BY messages.timestamp')
        for topic, msgtype, timestamp, data in rows:
            yield BagMessage(topic, msgtype, int(timestamp), bytes(data))
    finally:
        conn.close()


def _unfinished_storage(path: Path) -> Optional[Path]:
    """Find the single storage file of a bag directory without metadata.yaml, if any."""
    if not path.is_dir() or (path / 'metadata.yaml').exists():
        return None
    files = sorted(path.glob('*.mcap')) + sorted(path.glob('*.db3'))
    return files[0] if len(files) == 1 else None


def _open_reader(path: os.PathLike | str) -> Any:
    from rosbags.rosbag2 import Reader

    p = Path(path)
    if not p.exists():
        raise BagError(f'bag {p} does not exist')
    if not (p / 'metadata.yaml').is_file():
        raise BagError(f'{p} is not a rosbag2 bag (no metadata.yaml in it)')
    try:
        reader = Reader(p)
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags raises several types for bad bags
        raise BagError(f'{p} is not a readable rosbag2 bag: {exc}') from exc
    return reader


def read_bag(path: os.PathLike | str, topics: Optional[Sequence[str]] = None
             ) -> Iterator[BagMessage]:
    """
    Messages of a bag in time order, optionally only ``topics``.

    A bag whose recorder was killed (no metadata.yaml) is salvaged: every message up to the
    last complete mcap chunk (sqlite3: the last commit) is read.

    :raises BagError: missing path, not a bag, or a requested topic is absent.
    """
    unfinished = _unfinished_storage(Path(path))
    if unfinished is not None:
        messages = list(salvage_mcap(unfinished) if unfinished.suffix == '.mcap'
                        else _salvage_sqlite(unfinished))
        available = {m.topic for m in messages}
        missing = sorted(set(topics or ()) - available)
        if missing:
            raise BagError(f'topic(s) {", ".join(missing)} not in bag; it has: '
                           + ', '.join(sorted(available)))
        yield from (m for m in messages if not topics or m.topic in topics)
        return
    reader = _open_reader(path)
    try:
        available = {c.topic for c in reader.connections}
        if topics:
            missing = sorted(set(topics) - available)
            if missing:
                raise BagError(f'topic(s) {", ".join(missing)} not in bag; it has: '
                               + ', '.join(sorted(available)))
        conns = [c for c in reader.connections if not topics or c.topic in topics]
        for conn, timestamp, data in reader.messages(connections=conns):
            yield BagMessage(conn.topic, conn.msgtype, int(timestamp), bytes(data))
    finally:
        reader.close()


def bag_summary(path: os.PathLike | str) -> Tuple[Dict[str, Tuple[str, int]], int, int]:
    """
    ``({topic: (type, count)}, first_ns, last_ns)``.

    per-topic counts, first/last stamps (of the salvaged messages for a bag that was never closed).
    """
    if _unfinished_storage(Path(path)) is not None:
        out: Dict[str, Tuple[str, int]] = {}
        stamps = []
        for m in read_bag(path):
            t, n = out.get(m.topic, (m.msgtype, 0))
            out[m.topic] = (t, n + 1)
            stamps.append(m.timestamp)
        return out, (min(stamps) if stamps else 0), (max(stamps) if stamps else 0)
    reader = _open_reader(path)
    try:
        out: Dict[str, Tuple[str, int]] = {}
        for c in reader.connections:
            t, n = out.get(c.topic, (c.msgtype, 0))
            out[c.topic] = (t, n + c.msgcount)
        if not reader.message_count:
            return out, 0, 0
        # rosbags' end_time is one past the last message's timestamp
        return out, int(reader.start_time), int(reader.end_time) - 1
    finally:
        reader.close()
