"""Recordings as sources of frames: image folders, video files and ROS bags.

:func:`open_source` turns a path into a :class:`Source`, whose :meth:`Source.batches`
streams gray frames in [0, 1] at the model's size, a batch at a time, so memory does not grow
with the length of the recording:

* a folder of images (the benchmark loaders' rules; a folder with ``metadata.yaml`` is a
  ROS 2 bag);
* a video file (:data:`~flyvpr.sources.video.VIDEO_EXTENSIONS`, decoded with PyAV);
* a ROS 1 ``.bag`` or a ROS 2 bag (``.db3`` / ``.mcap`` or its folder), read with rosbags:
  ``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` on one topic.

A live source, a network stream (``rtsp://``, ``http(s)://``, ``udp://``, ``tcp://`` ...) or a
camera device (``/dev/video0``), is a :class:`~flyvpr.sources.live.LiveSource` (:func:`is_live`
tells them apart): it hands over the newest frame whenever asked, instead of batches.

Video, bags and live sources need the ``recordings`` extra (``pip install
'flyvpr[recordings]'``); it is imported only when such a source is opened.
"""

from __future__ import annotations

from pathlib import Path

from .base import Batch, Every, RecordingError, Source, parse_every
from .folder import FolderSource
from .live import LiveFrame, LiveSource, is_live
from .positions import Positions, read_positions

__all__ = [
    "Batch",
    "Every",
    "FolderSource",
    "LiveFrame",
    "LiveSource",
    "Positions",
    "RecordingError",
    "Source",
    "is_live",
    "open_source",
    "parse_every",
    "read_positions",
]


def open_source(path, *, topic: str | None = None) -> Source:
    """The source a path names: image folder, video file or ROS bag.

    Parameters
    ----------
    path : str or Path
    topic : str, optional
        Image topic of a bag (needed when the bag has several).

    Raises
    ------
    FileNotFoundError
        If nothing exists at ``path``.
    RecordingError
        If it is not a readable recording, or a bag without the topic (the message lists the
        image topics it has).
    ValueError
        For a folder: :class:`~flyvpr.images.ImageFolderError` for a stray entry, a
        ``ValueError`` for a folder without images; and for a ``topic`` given with something
        that is not a bag.  (``RecordingError`` and ``ImageFolderError`` are ``ValueError``
        too: catching ``ValueError`` catches every refusal of the data.)
    ImportError
        Naming the ``recordings`` extra, when a video or bag is given without it.
    """
    from .rosbag import BAG_EXTENSIONS, BagSource
    from .video import VIDEO_EXTENSIONS, VideoSource

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"recording not found: {p}")
    is_bag = (p.is_dir() and (p / "metadata.yaml").is_file()) or (
        p.is_file() and p.suffix.lower() in BAG_EXTENSIONS
    )
    if topic is not None and not is_bag:
        raise ValueError(f"topic={topic}: {p} is not a ROS bag")
    if is_bag:
        return BagSource(p, topic)
    if p.is_dir():
        return FolderSource(p)
    if p.suffix.lower() in VIDEO_EXTENSIONS:
        return VideoSource(p)
    raise RecordingError(
        f"{p}: not a recording flyvpr reads (an image folder, a video file "
        f"{'/'.join(VIDEO_EXTENSIONS)} or a ROS bag {'/'.join(BAG_EXTENSIONS)})"
    )
