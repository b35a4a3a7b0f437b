"""A live view of a localization run in the Rerun viewer (``flyvpr localize --view``).

:class:`LiveView` logs, per frame, what the localizer saw and what it thinks, to the
`Rerun <https://rerun.io>`_ SDK, which serves its own web viewer (no internet needed: the
viewer ships inside the ``rerun-sdk`` wheel) and writes ``.rrd`` recordings to watch later
(``rerun trace.rrd``, or the viewer's *Open*).  Entities, all on the timeline ``frame`` (the
source's frame index) and ``time`` (the frame's timestamp):

=====================  ===============================================================
``query``              the query frame (a preview of the camera frame, or the
                       pre-processed gray frame of a recording)
``input``              the frame as the localizer sees it (gray, the map's size)
``match``              the matched place's thumbnail from the map
``filter/activity``    the filter's score row over the places (a bar chart; maps with
                       more than ``max_bars`` places are shown as the maximum over bins)
``fix/place``          the matched place (a scalar series)
``fix/confidence``     the confidence (a scalar series)
``fix/localized``      1 while the filter is localized, 0 while lost
``fix/events``         a text log line when the state changes or the filter relocates
``route/places``       the map's place positions (static; only when the map has them)
``route/position``     the matched place's position (only when the map has positions)
=====================  ===============================================================

Positions are drawn with y pointing up (the viewer's 2-D y axis points down, so y is
negated).  Needs the ``view`` extra (``pip install 'flyvpr[view]'``); it is imported only
when a view is opened.
"""

from __future__ import annotations

import math
import threading
import uuid
from pathlib import Path

import numpy as np

from ._io import make_folders, remove_folders

__all__ = ["LiveView", "DEFAULT_WEB_PORT", "DEFAULT_GRPC_PORT"]

#: port of the web viewer's page
DEFAULT_WEB_PORT = 9090
#: port of the gRPC server the web viewer reads the data from
DEFAULT_GRPC_PORT = 9876
#: a timestamp above this many seconds is Unix time (drawn as a date), below it a duration
_UNIX_AFTER = 1e8
#: the query preview is at most this wide (RGB, uncompressed: the web viewer shows raw images
#: at once, where it decodes a JPEG per frame; a recording's size is mostly this)
PREVIEW_WIDTH = 240


def _require_rerun():
    try:
        import rerun
    except ImportError:
        raise ImportError(
            "the live view needs the 'rerun-sdk' package: pip install 'flyvpr[view]'"
        ) from None
    return rerun


def _uint8(image) -> np.ndarray:
    """A gray or RGB image as uint8 (float images are taken to be in [0, 1])."""
    a = np.asarray(image)
    if a.dtype == np.uint8:
        return a
    return np.clip(np.rint(a.astype(np.float32) * 255.0), 0, 255).astype(np.uint8)


def _preview(query) -> np.ndarray:
    """A PyAV frame as RGB at most ``PREVIEW_WIDTH`` wide; an array as uint8."""
    if hasattr(query, "reformat"):
        w = min(query.width, PREVIEW_WIDTH)
        h = max(1, round(query.height * w / query.width))
        return query.reformat(width=w, height=h, format="rgb24").to_ndarray()
    return _uint8(query)


def _binned_max(row: np.ndarray, n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """The maximum of ``row`` over ``n_bins`` consecutive bins, and each bin's first place."""
    starts = np.arange(n_bins) * row.shape[0] // n_bins
    return np.maximum.reduceat(row, starts), starts


class LiveView:
    """Log a localization run to the Rerun viewer, frame by frame.

    Parameters
    ----------
    map_ : flyvpr.localization.maps.Map
        The map the run localizes against (its thumbnails and positions are shown).
    serve : bool
        Serve the web viewer (``web_port``) and the data (``grpc_port``) while the run
        lasts; both listen on every network interface, so a laptop on the robot's network
        can open ``http://ROBOT:web_port``.
    save : str or Path, optional
        Also write the recording to this ``.rrd`` file (missing folders are created).
    web_port, grpc_port : int
    memory_limit : str
        How much the server keeps for viewers that connect late (the oldest data goes
        first), such as ``"256MiB"``.
    max_bars : int
        At most this many bars in the activity chart.
    background : bool
        Log on a thread of its own, so that the caller never waits for the viewer: when it
        is still busy with a frame, the next one replaces the one waiting (the view then
        skips frames, counted in ``n_skipped``; the records are unaffected).

    Attributes
    ----------
    url : str or None
        The address to open in a browser (None without ``serve``).
    n_logged, n_skipped : int
        Frames shown, and frames the view skipped to keep up.

    Raises
    ------
    ImportError
        Naming the ``view`` extra, without ``rerun-sdk``.
    ValueError
        Without ``serve`` or ``save``, or for ``max_bars`` < 1.
    """

    def __init__(
        self,
        map_,
        *,
        serve: bool = True,
        save=None,
        web_port: int = DEFAULT_WEB_PORT,
        grpc_port: int = DEFAULT_GRPC_PORT,
        memory_limit: str = "256MiB",
        max_bars: int = 2048,
        background: bool = True,
    ):
        if not serve and save is None:
            raise ValueError("LiveView needs serve=True or a save path (or both)")
        if int(max_bars) < 1:
            raise ValueError(f"max_bars must be >= 1; got {max_bars}")
        rr = self._rr = _require_rerun()
        self.map_ = map_
        self.max_bars = int(max_bars)
        self.save = None if save is None else Path(save)
        self.url = None
        self.n_logged = self.n_skipped = 0
        self._radius = 1.0  # of the route's dots, metres (set from the route's extent)
        self._state = None
        self._cond = threading.Condition()
        self._pending: tuple | None = None  # the newest frame's arguments of _log, not yet drawn
        self._closing = False
        self._worker = None
        self._rec = rr.RecordingStream("flyvpr", recording_id=uuid.uuid4())
        sinks = []
        if serve:
            server = rr.GrpcServerSink(port=int(grpc_port), server_memory_limit=memory_limit)
            sinks.append(server)
        # rerun's sink opens the file itself and creates no folder: make the missing ones
        created = [] if self.save is None else make_folders(self.save.parent)
        try:
            if self.save is not None:
                sinks.append(rr.FileSink(str(self.save)))
            self._rec.set_sinks(*sinks, default_blueprint=self._blueprint())
        except BaseException:
            remove_folders(created)
            raise
        if serve:
            # the server listens on every interface (0.0.0.0); a browser connects to a host
            data_url = server.uri.replace("0.0.0.0", "localhost")
            rr.serve_web_viewer(web_port=int(web_port), open_browser=False, connect_to=data_url)
            self.url = f"http://localhost:{int(web_port)}/?url={data_url}"
        self._log_route()
        if background:
            self._worker = threading.Thread(target=self._drain, name="flyvpr-view", daemon=True)
            self._worker.start()

    def _blueprint(self):
        import rerun.blueprint as rrb

        right = [
            rrb.BarChartView(origin="filter/activity", name="filter activity over places"),
            rrb.TimeSeriesView(origin="fix/place", name="place"),
            rrb.TimeSeriesView(
                origin="fix",
                contents=["fix/confidence", "fix/localized"],
                name="confidence, localized",
            ),
        ]
        if self.map_.positions is not None:
            right.append(rrb.Spatial2DView(origin="route", name="position on the route"))
        return rrb.Blueprint(
            rrb.Horizontal(
                rrb.Vertical(
                    rrb.Spatial2DView(origin="query", name="query"),
                    rrb.Horizontal(
                        rrb.Spatial2DView(origin="input", name="what the localizer sees"),
                        rrb.Spatial2DView(origin="match", name="matched place"),
                    ),
                    rrb.TextLogView(origin="fix/events", name="events"),
                    row_shares=[3, 2, 1],
                ),
                rrb.Vertical(*right),
            ),
            collapse_panels=True,
        )

    def _log_route(self) -> None:
        rr = self._rr
        xy = self.map_.positions
        if xy is None:
            return
        known = np.isfinite(xy).all(axis=1)
        pts = np.c_[xy[known, 0], -xy[known, 1]]
        if len(pts) == 0:
            return
        # sizes in metres, from the route's extent, so that any route shows its dots
        span = float(np.ptp(pts, axis=0).max()) if len(pts) > 1 else 1.0
        self._radius = max(span, 1e-9) / 100.0
        self._rec.log(
            "route/places",
            rr.Points2D(pts, colors=[150, 150, 150], radii=self._radius / 3),
            static=True,
        )

    def log(
        self,
        frame: int,
        timestamp: float,
        query,
        place: int,
        confidence: float,
        state: str,
        scores,
        *,
        model_input=None,
        relocated: bool = False,
    ) -> None:
        """Log one frame.

        Parameters
        ----------
        frame : int
            The frame's index in the source.
        timestamp : float
            Seconds (NaN: not on the ``time`` timeline).
        query : ndarray, shape (H, W) or (H, W, 3), or av.VideoFrame
            The frame to show, uint8 (or float in [0, 1]); a PyAV frame is shown in colour
            at most ``PREVIEW_WIDTH`` (240) pixels wide.
        place : int
        confidence : float
        state : str
            ``"localized"`` or ``"lost"``.
        scores : ndarray, shape (n_places,)
            The filter's score row.
        model_input : ndarray, shape (h, w), optional
            The pre-processed frame the localizer saw.
        relocated : bool
            Whether the filter relocated at this frame.
        """
        item = (frame, timestamp, query, place, confidence, state, scores, model_input, relocated)
        if self._worker is None:
            self._log(*item)
            return
        with self._cond:
            if self._pending is not None:
                self.n_skipped += 1
            self._pending = item
            self._cond.notify()

    def _drain(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._closing:
                    self._cond.wait()
                if self._pending is None:
                    return
                item, self._pending = self._pending, None
            self._log(*item)

    def _log(
        self, frame, timestamp, query, place, confidence, state, scores, model_input, relocated
    ) -> None:
        rr, rec = self._rr, self._rec
        self.n_logged += 1
        rec.set_time("frame", sequence=int(frame))
        if math.isfinite(timestamp):
            if timestamp > _UNIX_AFTER:
                rec.set_time("time", timestamp=float(timestamp))
            else:
                rec.set_time("time", duration=float(timestamp))
        rec.log("query", rr.Image(_preview(query)))
        if model_input is not None:
            rec.log("input", rr.Image(_uint8(model_input)))
        if self.map_.thumbnails is not None:
            rec.log("match", rr.Image(self.map_.thumbnails[int(place)]))
        row = np.asarray(scores, np.float32)
        if row.shape[0] > self.max_bars:
            values, starts = _binned_max(row, self.max_bars)
            rec.log("filter/activity", rr.BarChart(values, abscissa=starts.astype(np.float64)))
        else:
            rec.log("filter/activity", rr.BarChart(row))
        rec.log("fix/place", rr.Scalars(float(place)))
        rec.log("fix/confidence", rr.Scalars(float(confidence)))
        rec.log("fix/localized", rr.Scalars(1.0 if state == "localized" else 0.0))
        if state != self._state:
            rec.log("fix/events", rr.TextLog(f"frame {frame}: {state} at place {place}"))
            self._state = state
        elif relocated:
            rec.log("fix/events", rr.TextLog(f"frame {frame}: relocated to place {place}"))
        xy = self.map_.positions
        if xy is not None and np.isfinite(xy[int(place)]).all():
            x, y = xy[int(place)]
            rec.log(
                "route/position",
                rr.Points2D(
                    [[x, -y]], colors=[230, 40, 40], radii=self._radius, labels=[str(place)]
                ),  # fmt: skip
            )

    def close(self) -> None:
        """Log the frame still waiting, flush the recording (the ``.rrd`` file is complete
        after this) and stop serving."""
        if self._worker is not None:
            with self._cond:
                self._closing = True
                self._cond.notify()
            self._worker.join()
            self._worker = None
        self._rec.flush()
        self._rec.disconnect()

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
