"""Image folders: the frames of :func:`flyvpr.images.list_images`, read one at a time.

A folder has no clock: timestamps are NaN unless a positions CSV keyed by timestamp is given
elsewhere.  Decoding and resizing are those of the benchmark loaders (Pillow, ITU-R BT.601
luma, area averaging), so a folder gives exactly the images ``flyvpr evaluate`` reads.
"""

from __future__ import annotations

from collections.abc import Iterator
from functools import partial

from ..images import list_images, load_image
from .base import Decoder, Source

__all__ = ["FolderSource"]


class FolderSource(Source):
    """Every frame of an image folder, in natural name order."""

    kind = "image folder"

    def __init__(self, path):
        super().__init__(path)
        self.files = list_images(self.path)

    def _frames(self) -> Iterator[tuple[int, float, Decoder]]:
        for index, path in enumerate(self.files):
            yield index, float("nan"), partial(load_image, path)
