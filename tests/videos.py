"""Videos of the kinds cameras and editors make, written with PyAV for the tests: several
video streams, uneven timestamps, a silent audio track."""

from __future__ import annotations

from fractions import Fraction

import numpy as np


def write_av(path, streams, *, audio_s=0.0, container_options=None):
    """Encode a test video with PyAV.  ``streams``: dicts with ``frames`` (n, H, W, 3) uint8
    and optionally ``pts`` (in ``time_base``, default 1/10 s), ``codec`` (ffv1),
    ``pix_fmt`` (yuv444p), ``default`` (the stream's default disposition).  ``audio_s``:
    also a silent mono audio track of that many seconds."""
    import av

    with av.open(str(path), "w", options=container_options or {}) as c:
        outs = []
        for spec in streams:
            n, h, w = spec["frames"].shape[:3]
            s = c.add_stream(spec.get("codec", "ffv1"), rate=10)
            s.width, s.height, s.pix_fmt = w, h, spec.get("pix_fmt", "yuv444p")
            if "default" in spec:
                s.disposition = av.stream.Disposition.default if spec["default"] else 0
            outs.append(s)
        audio = None
        if audio_s:
            audio = c.add_stream("pcm_s16le", rate=8000)
            audio.layout = "mono"
        for s, spec in zip(outs, streams, strict=True):
            tb = spec.get("time_base", Fraction(1, 10))
            for i, rgb in enumerate(spec["frames"]):
                frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
                frame.pts, frame.time_base = spec.get("pts", range(len(spec["frames"])))[i], tb
                c.mux(s.encode(frame))
            c.mux(s.encode(None))
        if audio is not None:
            for k in range(int(audio_s)):
                silence = av.AudioFrame.from_ndarray(
                    np.zeros((1, 8000), np.int16), format="s16", layout="mono"
                )
                silence.sample_rate, silence.pts = 8000, k * 8000
                c.mux(audio.encode(silence))
            c.mux(audio.encode(None))
    return path
