"""Tag measurements of ``ppoe evaluate``: recorded observations, or tag detections on the bag's images made by
worker processes started early (:class:`TagStream`)."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import numpy as np

from ppoe_core.errors import BagError

__all__ = ["IMAGE_WORKERS", "TagStream", "tag_measurements"]

#: worker processes (or threads) decoding images and detecting tags (two, or one on a single core)
IMAGE_WORKERS = min(2, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


def _camera_lookup(data: Any, effects: Any = ()) -> Callable[[str, float], tuple[np.ndarray, np.ndarray] | None]:
    """frame_id, stamp -> (K, D) of the latest camera_info of that frame at or before the stamp
    (or the first one after it if there is none before), corrected by the model's ``camera_intrinsics`` of that
    frame (a diagnosed model)."""
    ci = data.camera_info
    intrinsics = {e.location: e for e in effects if e.name == "camera_intrinsics"}
    per: dict[str, tuple[np.ndarray, list[int]]] = {}
    for i, f in enumerate(ci.frame_ids):
        per.setdefault(f, (np.zeros(0), []))[1].append(i)
    table = {f: (ci.stamps[idx], idx) for f, (_, idx) in per.items()}

    def lookup(frame: str, stamp: float) -> tuple[np.ndarray, np.ndarray] | None:
        if frame not in table:
            return None
        st, idx = table[frame]
        k = int(np.searchsorted(st, stamp, side="right")) - 1
        i = idx[max(k, 0)]
        return intrinsics[frame].corrected(ci.K[i], ci.D[i]) if frame in intrinsics else (ci.K[i], ci.D[i])

    return lookup


def load_image_kernels() -> None:
    """Load the compiled kernels the image workers call (PNG unfiltering, the edge fit) in this process: a worker
    process forked before they are loaded loads them from the compile cache itself, at every evaluation."""
    from ppoe_core.io.png_kernel import unfilter_sub
    from ppoe_core.sensing.tags import refine_edges

    unfilter_sub(np.frombuffer(bytes(2), dtype=np.uint8).reshape(1, 2), 1)  # read-only rows, as decode_png's
    grey = np.full((16, 16), 255, dtype=np.uint8)
    grey[4:12, 4:12] = 0
    refine_edges(grey, np.array([[4.0, 4.0], [11.0, 4.0], [11.0, 11.0], [4.0, 11.0]]), 4, passes=1)


class TagStream:
    """The tag measurements of a bag, one slot per recorded ``/tag_bearing/observations`` message or per camera
    image (``stamps``), :meth:`get` the measurement of a slot (None: no tag point).

    Recorded observations are used as they are (made at once).  Otherwise the images are decoded and their tags
    detected (``ppoe_core.sensing.tags.detect_tags``, as the tag node; its rows by
    :func:`ppoe_core.sensing.tag_rows.rows_from_detections`) by ``workers`` processes forked here
    (:class:`ppoe_core.sensing.forked.ForkedResults`; ``processes`` False, or no ``fork`` on this platform: threads,
    :class:`ppoe_core.sensing.tag_rows.ImageDetections`; one worker: in the caller's thread, when asked), running
    while the caller does other work (``ppoe evaluate``: the replay); the images are handed out in image order, with
    the first error (no camera_info, an image that does not decode) at its image, as one loop over the images would.
    ``counts``: tag_messages, tag_points, images, images_without_tags (complete once every slot was read).  Call
    :meth:`close` at the end (stops the workers).

    ``priors``: ``(stamps, Q)`` of the forward kinematics' joint states (``model.joint_names`` order): the model's
    tags are then looked for in windows around their predicted corners
    (:func:`ppoe_core.analysis.evaluate.tag_prediction.predicted_windows`,
    :func:`ppoe_core.sensing.tag_rows.detect_tags_windowed`: the same corners as on the whole image, which is
    searched where the windows cannot promise that; ``windowed`` says which images the windows gave).
    """

    def __init__(self, data: Any, model: Any, bag: str, refine: str = "subpix", workers: int = IMAGE_WORKERS,
                 priors: tuple[np.ndarray, np.ndarray] | None = None, processes: bool = True) -> None:
        from ppoe_core.estimation.pipeline import Measurement, TagMeasurement, source_key

        self.counts = {"tag_messages": 0, "tag_points": 0, "images": 0, "images_without_tags": 0}
        self._out: list[Any] = []
        self._dets: Any = None
        self._camera: Any = None
        self.stamps: list[float] = []
        #: per detected image (in image order), True if the windows predicted from ``priors`` gave its tags
        #: (:func:`ppoe_core.sensing.tag_rows.detect_tags_windowed`), False for the whole image
        self.windowed: list[bool] = []
        cams = _camera_lookup(data, getattr(model, "effects", None) or ())  # no effects: camera_info as recorded
        obs = data.tag_observations
        if len(obs):
            topic = "/tag_bearing/observations"
            for i in range(len(obs)):
                m = obs.message(i)
                self.counts["tag_messages"] += 1
                if m["ids"].size == 0:
                    continue
                self.counts["tag_points"] += int(m["ids"].size)
                frame, stamp = obs.frame_ids[i], float(obs.stamps[i])
                KD = cams(frame, stamp)
                fx, fy = (float(KD[0][0, 0]), float(KD[0][1, 1])) if KD is not None else (None, None)
                payload = TagMeasurement(frame, m["ids"], m["corners"], m["xy"], m["uv"], fx, fy)
                self._out.append(Measurement(stamp, source_key(topic, frame), payload))
            self.stamps = [m.stamp for m in self._out]
            return
        self._imgs = imgs = data.images
        if len(imgs) == 0 or model.config.tags is None:
            return
        self.stamps = [float(t) for t in imgs.stamps]
        self._start(cams, model, refine, workers, bag, priors, processes)

    def _start(self, cams: Callable[[str, float], Any], model: Any, refine: str, workers: int, bag: str,
               priors: tuple[np.ndarray, np.ndarray] | None, processes: bool) -> None:
        from ppoe_core.analysis.evaluate.tag_prediction import predicted_windows
        from ppoe_core.sensing.forked import FORK_AVAILABLE, ForkedResults
        from ppoe_core.sensing.tag_rows import ImageDetections, detect_tags_windowed, rows_from_detections

        imgs = self._imgs

        def camera(i: int) -> tuple[np.ndarray, np.ndarray]:
            KD = cams(imgs.frame_ids[i], self.stamps[i])
            if KD is None:
                raise BagError(f"bag {bag}: topic {imgs.topic} message {i}: no /camera/camera_info with frame_id "
                               f"{imgs.frame_ids[i]!r}")
            return KD

        def known_camera(i: int) -> tuple[np.ndarray, np.ndarray] | None:
            return cams(imgs.frame_ids[i], self.stamps[i])

        family = model.config.tags.family
        windows: list[Any] = [None] * len(imgs)
        ids: list[int] = []
        if priors is not None:
            windows = predicted_windows(model, imgs.frame_ids, np.asarray(self.stamps), known_camera, *priors)
            ids = [item.id for item in model.config.tags.items]

        def one(i: int) -> tuple[np.ndarray, bool]:
            K, D = camera(i)  # its error first, as for an image that does not decode
            dets, windowed = detect_tags_windowed(imgs.decode(i), windows[i], family, refine, ids)
            return rows_from_detections(dets, K, D)[0], windowed  # = observe_tags(imgs.decode(i), K, D, family, ...)

        self._camera = camera
        if processes and FORK_AVAILABLE and workers > 1 and len(imgs) > 1:
            load_image_kernels()
            self._dets = ForkedResults(one, len(imgs), workers)
        else:  # threads (the rows made on them too: 0.11 ms per image holding the GIL), or the caller alone
            self._dets = ImageDetections(one, len(imgs), workers, len(imgs))

    def get(self, k: int) -> Any:
        """The measurement of slot ``k`` (None: an image without tags); reads the images up to ``k`` in order."""
        while len(self._out) <= k:
            self._out.append(self._image(len(self._out)))
        return self._out[k]

    def _image(self, i: int) -> Any:
        from ppoe_core.estimation.pipeline import Measurement, TagMeasurement, source_key

        self.counts["images"] += 1
        rows, windowed = next(self._dets)
        self.windowed.append(windowed)
        K, D = self._camera(i)
        self.counts["tag_messages"] += 1
        if rows.shape[0] == 0:
            self.counts["images_without_tags"] += 1
            return None
        self.counts["tag_points"] += int(rows.shape[0])
        ids, corners = np.rint(rows[:, 0]).astype(int), np.rint(rows[:, 1]).astype(int)
        frame = self._imgs.frame_ids[i]
        payload = TagMeasurement(frame, ids, corners, rows[:, 4:6], rows[:, 2:4], float(K[0, 0]), float(K[1, 1]))
        return Measurement(self.stamps[i], source_key("/tag_bearing/observations", frame), payload)

    def measurements(self) -> list[Any]:
        """Every slot's measurement (those with tags), in slot order."""
        if self.stamps:
            self.get(len(self.stamps) - 1)
        return [m for m in self._out if m is not None]

    def close(self) -> None:
        """Stop the detection workers."""
        if self._dets is not None:
            self._dets.close()


def tag_measurements(
    data: Any, model: Any, bag: str, refine: str = "subpix", workers: int = IMAGE_WORKERS
) -> tuple[list[Any], dict[str, int]]:
    """Measurements of tag observations: recorded ``/tag_bearing/observations`` if present,
    else detections on the camera images (``ppoe_core.sensing.tags.detect_tags``, as the tag node; decoded
    and detected on ``workers`` threads, the results taken in image order, the same for any ``workers``);
    :class:`TagStream` read to the end."""
    stream = TagStream(data, model, bag, refine, workers)
    try:
        return stream.measurements(), stream.counts
    finally:
        stream.close()

