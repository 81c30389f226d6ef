"""A robot's frame sources: a folder of images or synthetic scenes, encoded once (split out of
:mod:`scmr_mesh.mesh.robot`).
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from scmr_mesh.errors import InputError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


# ---------------------------------------------------------------- frames
#: JPEG quality of the frames a robot sends (``--jpeg-quality``; the thesis's
#: frames were 80-130 KB JPEGs).  Equal to ``scmr_mesh.imaging.codec.JPEG_QUALITY``
#: (not imported, to keep this module light).  0 sends lossless PNG instead.
JPEG_QUALITY = 90
#: An ``--images`` folder with at most this many files is read and re-encoded
#: once, before the robot is ready, instead of again every cycle.
ENCODE_CACHE_FILES = 64


@dataclass
class Frame:
    """One frame to send: encoded bytes, and how to get its pixels."""

    name: str
    data: bytes
    encoding: str
    shape: list | None = None
    rgb: Any = None  # (H, W, 3) uint8 when already known

    def pixels(self):
        if self.rgb is None:
            import cv2
            import numpy as np

            arr = cv2.imdecode(np.frombuffer(self.data, np.uint8), cv2.IMREAD_COLOR)
            self.rgb = None if arr is None else np.ascontiguousarray(arr[:, :, ::-1])
        return self.rgb


def check_jpeg_quality(quality: int) -> int:
    """``--jpeg-quality``: 1..100, or 0 for lossless PNG; anything else is an InputError."""
    try:
        q = int(quality)
    except (TypeError, ValueError):
        raise InputError(f"--jpeg-quality must be an integer 0..100, got {quality!r}") from None
    if not 0 <= q <= 100 or q != quality:
        raise InputError(f"--jpeg-quality must be 1..100 (or 0 for lossless PNG), got {quality}")
    return q


def _encode(rgb, jpeg_quality: int) -> tuple[bytes, str]:
    from scmr_mesh.imaging import encode_jpeg, encode_png

    if jpeg_quality == 0:
        return encode_png(rgb), "png"
    return encode_jpeg(rgb, quality=jpeg_quality), "jpeg"


def image_frames(folder: str | Path, *, jpeg_quality: int = JPEG_QUALITY) -> Iterator[Frame]:
    """Cycle forever over the PNG/JPEG files of ``folder`` (sorted by name).

    JPEG files are sent as they are (re-encoding would lose quality twice);
    PNG files are re-encoded as JPEG at ``jpeg_quality`` (sent unchanged
    when it is 0).

    Raises
    ------
    InputError
        At once (not at the first frame) when the folder is missing or holds
        no PNG/JPEG file, or ``jpeg_quality`` is out of range.
    """
    jpeg_quality = check_jpeg_quality(jpeg_quality)
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"--images {folder} is not a folder; pass a folder of PNG/JPEG frames")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not files:
        raise InputError(f"--images {folder} holds no .png/.jpg/.jpeg file")
    cache: dict[Path, Frame] = {}

    def load(p: Path) -> Frame:
        try:
            data = p.read_bytes()
        except OSError as exc:
            raise InputError(f"--images {folder}: cannot read {p.name} ({exc.strerror}); "
                             "make it readable or remove it from the folder") from None
        if p.suffix.lower() != ".png":
            return Frame(p.name, data, "jpeg")
        if jpeg_quality == 0:
            return Frame(p.name, data, "png")
        from scmr_mesh.imaging import decode_image

        try:
            rgb = decode_image(data)
        except InputError as exc:  # send it as it is: the server's error reply reports it
            log.warning("%s: not re-encoded as JPEG (%s); sent as it is", p.name, exc)
            return Frame(p.name, data, "png")
        enc, kind = _encode(rgb, jpeg_quality)
        return Frame(p.name, enc, kind, rgb=rgb)

    if len(files) <= ENCODE_CACHE_FILES:  # loaded up front, before the robot is ready, not while it sends
        for p in files:
            cache[p] = load(p)

    def gen() -> Iterator[Frame]:
        for p in itertools.cycle(files):
            frame = cache.get(p)
            yield frame if frame is not None else load(p)  # a bigger folder: read (and re-encoded) each cycle

    return gen()


#: How many distinct synthetic scenes a robot cycles through (the thesis gave
#: each robot an image set of 5; generating a scene costs 20-30 ms of CPU, so a
#: fleet that drew a new one per frame would load the host more than the
#: pipeline does).
SYNTHETIC_SET = 8


def synthetic_frames(kind: str, *, seed: int = 0, distinct: int = SYNTHETIC_SET,
                     jpeg_quality: int = JPEG_QUALITY) -> Iterator[Frame]:
    """Endless synthetic scenes of ``kind``: ``distinct`` scenes seeded
    ``seed .. seed+distinct-1``, each generated and encoded (JPEG at
    ``jpeg_quality``, PNG when it is 0) once, up front, and then cycled.

    ``kind="stub"`` uses :func:`scmr_mesh.mesh.testing.synthetic_png` (always PNG)
    and needs no imaging module; other kinds come from ``scmr_mesh.imaging.synthetic``.

    Raises
    ------
    InputError
        At once when ``kind`` is unknown or ``jpeg_quality`` out of range.
    """
    jpeg_quality = check_jpeg_quality(jpeg_quality)
    if kind == "stub":
        from scmr_mesh.mesh.testing import synthetic_png

        def stub() -> Iterator[Frame]:
            for i in itertools.count():
                yield Frame(f"stub-{seed + i}.png", synthetic_png(seed + i), "png")

        return stub()
    try:
        from scmr_mesh.imaging.synthetic import SCENE_KINDS, make_scene
    except ImportError as exc:
        raise InputError(f"--synthetic {kind}: synthetic scenes unavailable ({exc}); use --synthetic stub") from None
    if kind not in SCENE_KINDS:
        raise InputError(f"--synthetic must be one of {', '.join(SCENE_KINDS)} or stub, got {kind!r}")
    ext = ".png" if jpeg_quality == 0 else ".jpg"

    # made here, before the robot is ready, not while it sends: 10-33 ms of CPU a scene, which
    # 16 robots making their first 8 at 5 Hz on one host took from the cloud (ToR p99 over 100 ms
    # in the first 2 s of `scmr bench mesh`)
    made: list[Frame] = []
    for i in range(distinct):
        rgb, _truth = make_scene(kind, seed=seed + i)
        data, enc = _encode(rgb, jpeg_quality)
        made.append(Frame(f"{kind}-{seed + i}{ext}", data, enc, rgb=rgb))
    return itertools.cycle(made)


def bag_frames(path: str | Path, topic: str, *, jpeg_quality: int = JPEG_QUALITY) -> Iterator[Frame]:
    """Cycle forever over the images of ``topic`` in a ROS 2 recording (rosbag2 folder, ``.db3`` or ``.mcap``).

    ``CompressedImage`` JPEG/PNG messages are sent as they are; ``Image`` messages (8-bit
    encodings) are encoded as JPEG at ``jpeg_quality`` (PNG when 0).  A message that is not
    an image the mesh can segment (:class:`scmr_mesh.ros.wire.RosWireError`) is skipped,
    counted and logged once per reason; a pass with none usable is an :class:`InputError`.
    Frames are named ``<topic>@<stamp sec>.<nanosec>`` in the records.

    Raises
    ------
    InputError
        At once when the recording cannot be read or the topic is missing, empty or not an image.
    """
    from scmr_mesh.ros import bag as rosbag
    from scmr_mesh.ros import wire as rw

    jpeg_quality = check_jpeg_quality(jpeg_quality)
    bt = rosbag.find_topic(path, topic)
    skipped: dict[str, int] = {}

    def frame(payload: bytes) -> Frame:
        if bt.ros_type == rw.COMPRESSED_IMAGE:
            msg = rw.decode_compressed(payload)
            return Frame(f"{topic}@{msg.header.sec}.{msg.header.nanosec:09d}", msg.data,
                         rw.compressed_kind(msg.format, msg.data))
        img = rw.decode_image(payload)
        rgb = rw.image_to_rgb(img)
        data, enc = _encode(rgb, jpeg_quality)
        return Frame(f"{topic}@{img.header.sec}.{img.header.nanosec:09d}", data, enc, rgb=rgb)

    def gen() -> Iterator[Frame]:
        while True:
            good = 0
            for _ts, payload in rosbag.messages(bt):
                try:
                    f = frame(payload)
                except rw.RosWireError as exc:
                    skipped[exc.reason] = skipped.get(exc.reason, 0) + 1
                    if skipped[exc.reason] == 1:
                        log.error("--bag %s %s: message skipped (%s): %s; further ones are counted", path, topic,
                                  exc.reason, exc)
                    continue
                good += 1
                yield f
            if not good:
                raise InputError(f"--bag {path}: no message of {topic} is an image the mesh can segment "
                                 f"(skipped: {skipped})")

    gen.skipped = skipped  # type: ignore[attr-defined]
    return gen()


# ----------------------------------------------------------------- robot

def frames_from_args(images: str | None, synthetic: str | None, *, seed: int = 0,
                     jpeg_quality: int = JPEG_QUALITY, bag: str | None = None,
                     topic: str | None = None) -> Iterator[Frame]:
    """The frame source of ``--images DIR``, ``--synthetic KIND`` or ``--bag FILE --topic T`` (``--jpeg-quality``)."""
    if sum(x is not None for x in (images, synthetic, bag)) != 1:
        raise InputError("give exactly one of --images DIR, --synthetic KIND or --bag FILE")
    if bag is not None:
        if topic is None:
            raise InputError("--bag needs --topic TOPIC, e.g. --topic /camera/image_raw")
        return bag_frames(bag, topic, jpeg_quality=jpeg_quality)
    if topic is not None:
        raise InputError("--topic goes with --bag FILE; drop it or add --bag")
    if images is not None:
        return image_frames(images, jpeg_quality=jpeg_quality)
    return synthetic_frames(synthetic, seed=seed, jpeg_quality=jpeg_quality)


def pick_seed(robot_id: str) -> int:
    """A stable per-robot seed (so robots do not send identical synthetic frames)."""
    return sum(ord(c) * 131 ** i for i, c in enumerate(robot_id)) % 100_000
