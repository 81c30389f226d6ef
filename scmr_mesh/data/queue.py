"""A bounded, append-only, on-disk queue of one robot's telemetry.

While no tier acknowledges a robot's telemetry, the robot keeps it here and
replays it after reconnection; a robot restarted mid-outage finds its queue
again.  Layout of the queue folder::

    seg-000000000001.log   records with seq >= 1 (the name is the segment's first seq)
    seg-000000000513.log   the active segment (appends go here)
    ack                    highest acknowledged seq (text), replaced atomically

Record framing (little endian): ``b"SQ01" | u32 length | u64 seq |
u32 crc32(length, seq) | u32 crc32(payload) | payload``.  The header has its
own CRC so that a torn tail (a complete, valid header whose payload is cut
short, or a cut header) can be told from a corrupted length field.

The ``head`` file holds the highest seq handed out (20 digits and a newline,
rewritten in place after each append's segment write, so a process crash
never loses it).  It tells a *torn append* from a *truncated record*: a record
cut off at the tail whose seq is at most ``head`` had been appended (its
append returned, and under ``"always"`` it was fsynced), so it is counted in
``lost_seqs`` and its seq is never reused; a cut record beyond ``head`` is an
append that never returned (torn), which never had a seq.

Durability (``fsync`` policy):

* ``"always"`` (default): every :meth:`TelemetryQueue.append` fsyncs the
  segment before it returns, so an appended record survives a crash or power
  loss.  A crash in the middle of an append leaves a torn tail, which the next
  open detects, reports (``torn_bytes``) and truncates; that append never
  returned, so its seq was never handed out.
* ``"batch"``: fsync every ``fsync_every`` appends and on ack/close; a power
  loss can lose the last unsynced records (a process crash cannot: the OS keeps
  written pages); when it does, their seqs are in ``lost_seqs`` (``head``).
* ``"never"``: leave it to the OS.

The ``ack`` file (fixed width) is written and synced before any fully
acknowledged segment is deleted (created once through a temporary file and a
rename, then overwritten in place), and the active segment's name carries
its first seq, so seqs are never reused after a restart.

Appends are single ``os.write`` calls on an unbuffered descriptor: no record
ever waits in a user-space buffer.  When the file system refuses an append
(``ENOSPC`` on a full disk, ``EPERM`` on an immutable file, ``EIO``) the
segment is truncated back to its length before the call, so it holds exactly
what it held before, and :class:`QueueWriteError` is raised; nothing written
later can land behind a partial record.

Refusals (full queue or :class:`QueueWriteError`) are counted in ``refused``.
With ``refusals_use_seqs=True`` (a robot's own queue, whose caller embeds the
seq in the record) a refused record keeps its seq: it is listed in
``refused_seqs``, ``head`` moves past it, and the store sees the gap, so every
report counts it as lost.  Without it (the leader's relay queue, whose sender
keeps the records) a refusal hands out no seq.

Full queue: when unacknowledged records would exceed ``max_bytes`` the queue
refuses the new record with :class:`QueueFullError`; nothing already queued
is ever dropped.

Corruption: a record whose magic, length or CRC does not check out is
reported (an ERROR log line and ``stats().corruptions``), counted, and skipped
by re-synchronising on the next valid record; the seqs it held are listed in
``stats().lost_seqs``.  With ``strict=True`` opening raises
:class:`QueueCorruptError` instead.
"""

from __future__ import annotations

import logging
import os
import re
import struct
import threading
import zlib
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

from scmr_mesh.data.errors import QueueCorruptError, QueueError, QueueFullError, QueueWriteError

log = logging.getLogger(__name__)

MAGIC = b"SQ01"
HEADER = struct.Struct("<4sIQII")  # magic, length, seq, header crc, payload crc
_HCRC = struct.Struct("<IQ")
#: Largest payload one record may carry.
MAX_RECORD_BYTES = 1 << 20
FSYNC_POLICIES = ("always", "batch", "never")
_SEG_RE = re.compile(r"^seg-(\d{12})\.log$")
#: Name of the file holding the highest seq handed out (see the module docstring).
HEAD_FILE = "head"
_HEAD_FMT = "{:020d}\n"


def _hcrc(length: int, seq: int) -> int:
    return zlib.crc32(_HCRC.pack(length, seq)) & 0xFFFFFFFF


def encode_frame(seq: int, payload: bytes) -> bytes:
    """One framed record: header + payload."""
    return HEADER.pack(MAGIC, len(payload), seq, _hcrc(len(payload), seq), zlib.crc32(payload)) + payload


@dataclass(frozen=True)
class Corruption:
    """A stretch of a segment that did not parse (reported, never silent)."""

    file: str
    offset: int
    nbytes: int
    reason: str


@dataclass
class QueueStats:
    """Counters of a :class:`TelemetryQueue` (``to_dict`` for reports)."""

    depth: int = 0
    pending_bytes: int = 0
    next_seq: int = 1
    acked_seq: int = 0
    appended: int = 0
    refused: int = 0
    replayed: int = 0
    torn_bytes: int = 0
    corruptions: list[Corruption] = field(default_factory=list)
    lost_seqs: list[int] = field(default_factory=list)
    refused_seqs: list[int] = field(default_factory=list)
    last_error: str | None = None

    def to_dict(self) -> dict:
        d = dict(self.__dict__)
        d["corruptions"] = [c.__dict__ for c in self.corruptions]
        d["lost_seqs"] = list(self.lost_seqs)
        d["refused_seqs"] = list(self.refused_seqs)
        return d


def scan_segment(data: bytes, *, last: bool) -> tuple[list[tuple[int, bytes, int]], list[tuple[int, int, str]], int]:
    """Parse a segment's bytes.

    Parameters
    ----------
    data : bytes
        The whole segment file.
    last : bool
        Whether this is the active (last) segment: an incomplete record at its
        end is a torn tail, not a corruption.

    Returns
    -------
    records : list of (seq, payload, end_offset)
    bad : list of (offset, nbytes, reason)
        Stretches skipped as corrupt.
    torn_at : int
        Offset where a torn tail starts (``len(data)`` when there is none).
    """
    records: list[tuple[int, bytes, int]] = []
    bad: list[tuple[int, int, str]] = []
    pos, n = 0, len(data)
    bad_start: int | None = None
    bad_reason = ""

    def parse_at(p: int) -> tuple[str, int, bytes, int]:
        if n - p < HEADER.size:
            return "short", 0, b"", 0
        magic, length, seq, hcrc, pcrc = HEADER.unpack_from(data, p)
        if magic != MAGIC:
            return "bad magic", 0, b"", 0
        if _hcrc(length, seq) != hcrc:
            return "header crc mismatch", 0, b"", 0
        if length > MAX_RECORD_BYTES:
            return f"length {length} > {MAX_RECORD_BYTES}", 0, b"", 0
        end = p + HEADER.size + length
        if end > n:
            return "short", 0, b"", 0
        payload = data[p + HEADER.size:end]
        if zlib.crc32(payload) != pcrc:
            return "payload crc mismatch", 0, b"", 0
        return "", seq, payload, end

    def _valid_after(p: int) -> bool:
        q = data.find(MAGIC, p + 1)
        while q >= 0:
            if not parse_at(q)[0]:
                return True
            q = data.find(MAGIC, q + 1)
        return False

    while pos < n:
        why, seq, payload, end = parse_at(pos)
        if not why:
            if bad_start is not None:
                bad.append((bad_start, pos - bad_start, bad_reason))
                bad_start = None
            records.append((seq, payload, end))
            pos = end
            continue
        if why == "short" and bad_start is None and last and not _valid_after(pos):
            return records, bad, pos  # torn tail: an append that never completed
        if bad_start is None:
            bad_start, bad_reason = pos, why
        nxt = data.find(MAGIC, pos + 1)
        if nxt < 0:
            pos = n
            break
        pos = nxt
    if bad_start is not None:
        bad.append((bad_start, n - bad_start, bad_reason))
    return records, bad, n


class TelemetryQueue:
    """Bounded on-disk FIFO of ``(seq, payload)`` with acknowledgements.

    Parameters
    ----------
    path : str or Path
        The queue's folder (one per robot); created if missing.
    max_bytes : int
        Bound on unacknowledged payload bytes (framing excluded).
    segment_bytes : int
        Roll over to a new segment file beyond this size.
    fsync : {"always", "batch", "never"}
        Durability policy (module docstring).
    fsync_every : int
        Appends between fsyncs under ``"batch"``.
    strict : bool
        Raise :class:`QueueCorruptError` on a corrupt record instead of
        reporting and skipping it.
    readonly : bool
        Inspect only (another process may be appending): no repair, no
        writes; :meth:`append` and :meth:`ack` raise :class:`QueueError`.
    refusals_use_seqs : bool
        A refused append keeps its seq (``refused_seqs``; the store sees the
        gap and reports count it as lost).  For a queue whose caller embeds
        the seq in the record before appending (a robot's telemetry).

    Examples
    --------
    >>> import tempfile
    >>> q = TelemetryQueue(tempfile.mkdtemp())
    >>> q.append(b"a"), q.append(b"b")
    (1, 2)
    >>> q.ack(1)
    1
    >>> [s for s, _ in q.pending()]
    [2]
    >>> q.close()
    """

    def __init__(self, path: str | Path, *, max_bytes: int = 16 << 20, segment_bytes: int = 1 << 20,
                 fsync: str = "always", fsync_every: int = 32, strict: bool = False,
                 readonly: bool = False, refusals_use_seqs: bool = False) -> None:
        if fsync not in FSYNC_POLICIES:
            raise QueueError(f"fsync policy must be one of {FSYNC_POLICIES}, got {fsync!r}")
        if max_bytes < 1 or segment_bytes < 1:
            raise QueueError(f"max_bytes and segment_bytes must be >= 1, got {max_bytes}, {segment_bytes}")
        self.path = Path(path)
        self.max_bytes = int(max_bytes)
        self.segment_bytes = int(segment_bytes)
        self.fsync = fsync
        self.fsync_every = max(1, int(fsync_every))
        self.refusals_use_seqs = bool(refusals_use_seqs)
        self._lock = threading.RLock()
        self._pending: deque[tuple[int, bytes]] = deque()
        self._segments: list[tuple[int, Path, int]] = []  # (first_seq, path, last_seq or first-1)
        self._fd: int | None = None      # the active segment, O_APPEND, unbuffered
        self._size = 0                   # its length after the last complete append
        self._dirty = False              # a failed append's bytes could not be truncated away
        self._head_fd: int | None = None
        self._ack_fd: int | None = None  # the ``ack`` file, overwritten in place (:meth:`_write_ack`)
        self._head_warned = False
        self._unsynced = 0
        self.stats_ = QueueStats()
        self.readonly = readonly
        if readonly:
            if not self.path.is_dir():
                raise QueueError(f"no telemetry queue folder at {str(self.path)!r}")
        else:
            try:
                self.path.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise QueueError(f"cannot create the queue folder {str(self.path)!r}: {exc}") from None
        self._recover(strict)

    # ---------------------------------------------------------------- recovery
    def _read_ack(self) -> int:
        return self._read_seq_file("ack", "replaying everything (the store de-duplicates)")

    def _read_head(self) -> int:
        return self._read_seq_file(HEAD_FILE, "a record cut off at the tail cannot be told from a torn append")

    def _read_seq_file(self, name: str, consequence: str) -> int:
        """The seq a small state file holds (0 when it is missing, or damaged: logged with its ``consequence``)."""
        f = self.path / name
        try:
            text = f.read_text().strip()
        except FileNotFoundError:
            return 0
        except OSError as exc:
            raise QueueError(f"cannot read {str(f)!r}: {exc}") from None
        if not text:  # created (the head at open) and never written: nothing handed out yet
            return 0
        if not text.isdigit():
            log.error("queue %s: %s file holds %r, not a seq; %s", self.path, name, text[:40], consequence)
            return 0
        return int(text)

    def _recover(self, strict: bool) -> None:
        st = self.stats_
        acked = self._read_ack()
        head = self._read_head()
        segs = sorted((int(m.group(1)), p) for p in self.path.iterdir()
                      if (m := _SEG_RE.match(p.name)))
        expected: int | None = None
        last_seq = acked
        for i, (first, seg) in enumerate(segs):
            is_last = i == len(segs) - 1
            data = seg.read_bytes()
            records, bad, torn_at = scan_segment(data, last=is_last)
            for off, nbytes, reason in bad:
                c = Corruption(str(seg), off, nbytes, reason)
                if strict:
                    raise QueueCorruptError(
                        f"queue segment {str(seg)!r}: {nbytes} corrupt bytes at offset {off} ({reason}); "
                        "open without strict to skip them (their seqs are reported as lost)")
                log.error("queue %s: %d corrupt bytes at offset %d (%s); skipped and counted",
                          seg, nbytes, off, reason)
                st.corruptions.append(c)
            if torn_at < len(data):
                st.torn_bytes += len(data) - torn_at
                if self.readonly:  # maybe an append in progress in the robot: look, never touch
                    log.info("queue %s: %d bytes at the tail are an incomplete record (torn, or being "
                             "written)", seg, len(data) - torn_at)
                else:
                    log.warning("queue %s: incomplete record of %d bytes at offset %d; truncated",
                                seg, len(data) - torn_at, torn_at)
                    with seg.open("r+b") as fh:
                        fh.truncate(torn_at)
                        os.fsync(fh.fileno())
            seg_last = first - 1
            if expected is None:
                expected = min(first, acked + 1)
            if first > expected:
                # records between the previous segment and this one are missing
                st.lost_seqs.extend(s for s in range(expected, first) if s > acked)
                expected = first
            for seq, payload, _end in records:
                if seq < expected:
                    log.error("queue %s: seq %d out of order (expected %d); ignored", seg, seq, expected)
                    st.corruptions.append(Corruption(str(seg), _end - len(payload) - HEADER.size,
                                                     len(payload) + HEADER.size, f"seq {seq} out of order"))
                    continue
                if seq > expected:
                    st.lost_seqs.extend(s for s in range(expected, seq) if s > acked)
                expected = seq + 1
                seg_last = seq
                if seq > acked:
                    self._pending.append((seq, payload))
                    st.pending_bytes += len(payload)
            if is_last and bad and bad[-1][0] >= (records[-1][2] if records else 0):
                # a corrupt stretch at the very end: its records' seqs must never be reused
                tail = _tail_seqs(data, bad[-1][0], bad[-1][1], max(seg_last, expected - 1))
                st.lost_seqs.extend(s for s in tail if s > acked)
                if tail:
                    seg_last = tail[-1]
                    expected = seg_last + 1
            self._segments.append((first, seg, seg_last))
            last_seq = max(last_seq, seg_last, first - 1)
        if head > last_seq:
            # handed out (appended, or refused keeping their seq) but not on disk: records
            # cut off at the tail (not torn appends: those never reached the head), or refusals
            gone = list(range(last_seq + 1, head + 1))
            st.lost_seqs.extend(gone)
            log.error("queue %s: %d record(s) handed out but missing at the tail (seq %s; cut off, or "
                      "refused when written); counted as lost, their seqs are not reused",
                      self.path, len(gone), ",".join(seq_ranges(gone, limit=5)))
            last_seq = head
        if st.lost_seqs:
            log.error("queue %s: %d seq(s) lost: %s", self.path, len(st.lost_seqs),
                      ",".join(seq_ranges(st.lost_seqs, limit=20)))
        st.acked_seq = acked
        st.next_seq = max(last_seq, acked) + 1
        st.depth = len(self._pending)
        if self.readonly:
            return
        if not (self.path / "ack").exists():
            try:  # made now, while there is room: a full disk later can still overwrite it in place
                self._write_ack(acked)
            except OSError as exc:
                log.warning("queue %s: cannot write its ack file (%s)", self.path, exc)
        try:
            self._head_fd = os.open(self.path / HEAD_FILE, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            self._head_fd = None
            log.warning("queue %s: cannot open its head file (%s); records cut off at the tail will "
                        "look like torn appends", self.path, exc)
        try:
            if not self._segments or (st.corruptions and st.corruptions[-1].file == str(self._segments[-1][1])):
                self._new_segment(st.next_seq)  # never append behind a corrupt stretch
            else:
                self._open_segment(self._segments[-1][1])
        except OSError as exc:
            self.close()
            raise QueueError(f"cannot open the telemetry queue {str(self.path)!r} for appending: {exc}") from None

    def _open_segment(self, seg: Path) -> None:
        fd = os.open(seg, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC, 0o644)
        old, self._fd = self._fd, fd
        self._size = os.fstat(fd).st_size
        if old is not None:
            os.close(old)

    def _new_segment(self, first: int) -> None:
        if self._fd is not None:
            self._sync(force=True)
        seg = self.path / f"seg-{first:012d}.log"
        self._open_segment(seg)
        self._fsync_dir()
        self._segments.append((first, seg, first - 1))

    def _fsync_dir(self) -> None:
        if self.fsync == "never":
            return
        fd = os.open(self.path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    def _sync(self, *, force: bool = False) -> None:
        """fsync the active segment per the policy (raises OSError)."""
        if self._fd is None or self.fsync == "never":
            return
        self._unsynced += 1
        if force or self.fsync == "always" or self._unsynced >= self.fsync_every:
            os.fsync(self._fd)
            self._unsynced = 0

    def _write_head(self, seq: int) -> None:
        """Record ``seq`` as handed out (in place; the page cache keeps it across a process crash)."""
        if self._head_fd is None:
            return
        try:
            os.pwrite(self._head_fd, _HEAD_FMT.format(seq).encode(), 0)
        except OSError as exc:
            if not self._head_warned:
                self._head_warned = True
                log.warning("queue %s: cannot update its head file (%s)", self.path, exc)

    def _rollback(self) -> None:
        """Cut the active segment back to its length before a failed append."""
        try:
            if os.fstat(self._fd).st_size != self._size:
                os.ftruncate(self._fd, self._size)
            self._dirty = False
        except OSError as exc:
            self._dirty = True
            log.error("queue %s: a failed append left bytes in the segment that cannot be truncated (%s); "
                      "every append is refused until it can", self.path, exc)

    # ---------------------------------------------------------------- API
    @property
    def next_seq(self) -> int:
        """The seq the next :meth:`append` will get."""
        return self.stats_.next_seq

    def __len__(self) -> int:
        return len(self._pending)

    def _refuse(self, seq: int, exc: QueueError) -> QueueError:
        st = self.stats_
        st.refused += 1
        st.last_error = str(exc)
        if self.refusals_use_seqs:
            st.refused_seqs.append(seq)
            st.next_seq = seq + 1
            self._write_head(seq)
        return exc

    def append(self, payload: bytes, *, seq: int | None = None) -> int:
        """Append a record durably (per the fsync policy); return its seq.

        Parameters
        ----------
        payload : bytes
            At most :data:`MAX_RECORD_BYTES`.
        seq : int, optional
            If given it must equal :attr:`next_seq` (lets the caller embed the
            seq in the payload first).

        Raises
        ------
        QueueFullError
            The unacknowledged records already hold ``max_bytes``; counted in ``refused``.
        QueueWriteError
            The file system refused the write or the fsync (full, read-only,
            immutable, I/O error); the segment holds exactly what it held
            before the call.  Counted in ``refused``.
        """
        if not isinstance(payload, (bytes, bytearray)):
            raise QueueError(f"queue payload must be bytes, got {type(payload).__name__}")
        if len(payload) > MAX_RECORD_BYTES:
            raise QueueError(f"queue record of {len(payload)} bytes exceeds {MAX_RECORD_BYTES}")
        with self._lock:
            st = self.stats_
            if self._fd is None:
                raise QueueError(f"queue {str(self.path)!r} is closed or read-only")
            if seq is not None and seq != st.next_seq:
                raise QueueError(f"append seq must be the next seq {st.next_seq}, got {seq}")
            seq = st.next_seq
            if st.pending_bytes + len(payload) > self.max_bytes:
                raise self._refuse(seq, QueueFullError(
                    f"telemetry queue {str(self.path)!r} is full: {st.depth} unacknowledged records, "
                    f"{st.pending_bytes} of {self.max_bytes} bytes; record {seq} was refused "
                    f"({st.refused + 1} refused so far); reconnect a tier to drain it or raise max_bytes"))
            frame = encode_frame(seq, bytes(payload))
            try:
                if self._dirty:
                    self._rollback()
                    if self._dirty:
                        raise OSError("bytes of an earlier failed append are still in the segment")
                if self._size >= self.segment_bytes:
                    self._new_segment(seq)
                view = memoryview(frame)
                while view:  # os.write may write part of it (a file system filling up)
                    n = os.write(self._fd, view)
                    view = view[n:]
                self._sync()
            except OSError as exc:
                if self._fd is not None:
                    self._rollback()
                raise self._refuse(seq, QueueWriteError(
                    f"telemetry queue {str(self.path)!r}: record {seq} could not be written "
                    f"({exc.strerror or exc}); the segment is unchanged; free space on that file "
                    f"system or make the queue folder writable ({st.refused + 1} refused so far)")) from None
            self._size += len(frame)
            self._write_head(seq)
            first, seg, _last = self._segments[-1]
            self._segments[-1] = (first, seg, seq)
            self._pending.append((seq, bytes(payload)))
            st.pending_bytes += len(payload)
            st.depth = len(self._pending)
            st.appended += 1
            st.next_seq = seq + 1
            return seq

    def free_bytes(self) -> int:
        """Payload bytes that can still be appended before the queue is full."""
        with self._lock:
            return self.max_bytes - self.stats_.pending_bytes

    def pending(self, *, limit: int | None = None, max_bytes: int | None = None,
                after: int = 0) -> list[tuple[int, bytes]]:
        """The oldest unacknowledged ``(seq, payload)`` pairs with ``seq > after``, in seq order."""
        out: list[tuple[int, bytes]] = []
        size = 0
        with self._lock:
            for seq, payload in self._pending:
                if seq <= after:
                    continue
                if limit is not None and len(out) >= limit:
                    break
                if max_bytes is not None and out and size + len(payload) > max_bytes:
                    break
                out.append((seq, payload))
                size += len(payload)
        return out

    def ack(self, upto_seq: int) -> int:
        """Acknowledge every record with ``seq <= upto_seq``; return how many left the queue."""
        if self.readonly:
            raise QueueError(f"queue {str(self.path)!r} was opened read-only; it cannot be acknowledged")
        with self._lock:
            st = self.stats_
            if upto_seq <= st.acked_seq:
                return 0
            upto_seq = min(upto_seq, st.next_seq - 1)
            n = 0
            while self._pending and self._pending[0][0] <= upto_seq:
                _, payload = self._pending.popleft()
                st.pending_bytes -= len(payload)
                n += 1
            st.acked_seq = upto_seq
            st.depth = len(self._pending)
            if self.fsync == "batch":
                self._sync(force=True)
            self._write_ack(upto_seq)
            # delete segments (not the active one) whose records are all acknowledged
            while len(self._segments) > 1 and self._segments[0][2] <= upto_seq:
                _, seg, _ = self._segments.pop(0)
                try:
                    seg.unlink()
                except FileNotFoundError:
                    pass
            return n

    def _write_ack(self, seq: int) -> None:
        """Record ``seq`` as acknowledged, durably (per the fsync policy) before it returns.

        The ``ack`` file has a fixed width (:data:`_HEAD_FMT`, 21 bytes, inside one sector): once it
        exists, each ack overwrites it in place through a descriptor kept open and ``fdatasync``s it,
        one flush of one block and no new blocks.  Until issue 23 every ack wrote ``ack.tmp``,
        fsynced it, renamed it over ``ack`` and fsynced the folder: two fsyncs, a create and a
        rename per flush, about 0.5 ms of a robot's CPU per ack (docs/BENCHMARKS.md "CPU per
        request").  Only the first ack of a folder is written that way.  In place also works on a
        full disk (a review of issue 25 item 2: before, a full disk kept the old ack, and a restart
        counted the records a store had taken from memory as lost)."""
        data = _HEAD_FMT.format(seq).encode()
        if self._ack_fd is None and (self.path / "ack").exists():
            fd = os.open(self.path / "ack", os.O_WRONLY | os.O_CLOEXEC)  # raises: the caller counts it
            if os.fstat(fd).st_size == len(data):
                self._ack_fd = fd
            else:  # damaged or of another width: replaced whole below (in place would leave a tail)
                os.close(fd)
        if self._ack_fd is not None:
            os.pwrite(self._ack_fd, data, 0)
            if self.fsync != "never":
                os.fdatasync(self._ack_fd)
            return
        tmp = self.path / "ack.tmp"
        try:
            with tmp.open("wb") as fh:
                fh.write(data)
                fh.flush()
                if self.fsync != "never":
                    os.fsync(fh.fileno())
            os.replace(tmp, self.path / "ack")
        except OSError:
            try:
                tmp.unlink()
            except OSError:
                pass
            if not (self.path / "ack").exists():
                raise
            fd = os.open(self.path / "ack", os.O_WRONLY | os.O_CLOEXEC)  # a full disk: no new blocks (as before)
            try:
                os.pwrite(fd, data, 0)
                if self.fsync != "never":
                    os.fsync(fd)
            finally:
                os.close(fd)
            return
        self._fsync_dir()
        try:
            self._ack_fd = os.open(self.path / "ack", os.O_WRONLY | os.O_CLOEXEC)
        except OSError:
            self._ack_fd = None

    def note_replayed(self, n: int) -> None:
        """Count records sent again after a failed attempt (for reports)."""
        with self._lock:
            self.stats_.replayed += n

    def stats(self) -> QueueStats:
        """A copy of the counters."""
        with self._lock:
            st = self.stats_
            return QueueStats(st.depth, st.pending_bytes, st.next_seq, st.acked_seq, st.appended,
                              st.refused, st.replayed, st.torn_bytes, list(st.corruptions),
                              list(st.lost_seqs), list(st.refused_seqs), st.last_error)

    def close(self) -> None:
        """fsync and close the active segment and the head file (idempotent; never raises)."""
        with self._lock:
            if self._ack_fd is not None:  # every ack was synced when written
                fd, self._ack_fd = self._ack_fd, None
                try:
                    os.close(fd)
                except OSError:
                    pass
            for name in ("_fd", "_head_fd"):
                fd = getattr(self, name)
                if fd is None:
                    continue
                setattr(self, name, None)
                try:
                    if self.fsync != "never":
                        os.fsync(fd)
                except OSError as exc:
                    log.error("queue %s: fsync at close failed: %s", self.path, exc)
                finally:
                    os.close(fd)

    def __enter__(self) -> "TelemetryQueue":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _tail_seqs(data: bytes, off: int, nbytes: int, last_good: int) -> list[int]:
    """Seqs a corrupt tail stretch probably held: from plausible headers, at least one."""
    hi = last_good + 1
    bound = last_good + nbytes // HEADER.size + 1
    p = data.find(MAGIC, off, off + nbytes)
    while p >= 0 and p + HEADER.size <= len(data):
        _, length, seq, hcrc, _ = HEADER.unpack_from(data, p)
        if _hcrc(length, seq) == hcrc and last_good < seq <= bound:
            hi = max(hi, seq)
        p = data.find(MAGIC, p + 1, off + nbytes)
    return list(range(last_good + 1, hi + 1))


def seq_ranges(seqs: list[int], *, limit: int | None = None) -> list[str]:
    """Compress sequence numbers into ranges: ``[1, 2, 3, 7]`` -> ``["1-3", "7"]``.

    ``limit`` keeps only the first that many ranges (for reports).
    """
    out: list[str] = []
    start = prev = None
    for s in sorted(seqs):
        if start is None:
            start = prev = s
        elif s == prev + 1:
            prev = s
        else:
            out.append(f"{start}-{prev}" if start != prev else str(start))
            start = prev = s
    if start is not None:
        out.append(f"{start}-{prev}" if start != prev else str(start))
    return out if limit is None else out[:limit]


__all__ = ["HEAD_FILE", "MAX_RECORD_BYTES", "Corruption", "QueueStats", "TelemetryQueue", "encode_frame", "scan_segment"]


#: File of a queue folder holding its incarnation (issue #25 item 10; see :func:`folder_incarnation`).
INCARNATION_FILE = "incarnation"


def folder_incarnation(path: str | Path) -> int:
    """The incarnation of the queue folder at ``path``: a random 63-bit id chosen when the folder is new.

    Records carry it (``TelemetryRecord.inc``) and the store keys them by ``(robot, inc, seq)``, so a
    robot whose queue folder was wiped (seqs from 1 again) starts a new history instead of colliding
    with the stored one.  Written once (temporary file, fsync, rename) and read back afterwards; a
    folder of an older version (segments, no incarnation file) keeps incarnation 0, so its replays
    still meet their stored copies.  When the file cannot be written (a full disk) the id is used for
    this process only and logged.
    """
    import secrets

    folder = Path(path)
    f = folder / INCARNATION_FILE
    try:
        text = f.read_text().strip()
    except FileNotFoundError:
        text = None
    except OSError as exc:
        raise QueueError(f"cannot read {str(f)!r}: {exc}") from None
    if text is not None:
        if text.isdigit() and int(text) < 2**63:
            return int(text)
        log.error("queue %s: %s file holds %r, not an incarnation; choosing a new one", folder,
                  INCARNATION_FILE, text[:40])
    try:
        folder.mkdir(parents=True, exist_ok=True)
        legacy = text is None and any(p.name in ("ack", HEAD_FILE) or _SEG_RE.match(p.name) for p in folder.iterdir())
    except OSError as exc:
        raise QueueError(f"cannot create the queue folder {str(folder)!r}: {exc}") from None
    inc = 0 if legacy else secrets.randbits(63) or 1
    tmp = folder / f".{INCARNATION_FILE}.tmp"
    try:
        with open(tmp, "w") as fh:
            fh.write(f"{inc}\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, f)
    except OSError as exc:
        log.error("queue %s: cannot write its incarnation (%s); incarnation %d holds for this process only",
                  folder, exc, inc)
    return inc
