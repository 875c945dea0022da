"""The build's extraction stage: every frame's features and working camera (:class:`FrameFeatures`),
extracted on an executor's workers (:class:`ExtractorSpec` is the picklable recipe a worker builds its
extractor from), optionally through the on-disk feature cache."""

from __future__ import annotations

import threading
from collections.abc import Sequence as SequenceABC
from dataclasses import dataclass, fields, is_dataclass, replace
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from . import features as feats_mod
from .executor import Executor, LocalExecutor
from .features import Extractor, Features
from .features.cache import FeatureCache, source_stamp
from .io import Camera, Sequence
from .io.images import decode_and_prepare, read_image_bytes


@dataclass
class FrameFeatures:
    """Stage boundary after extraction: features plus the working (undistorted, resized) cameras."""

    features: SequenceABC[Features]  # a list, or the frames of a FeatureCache (read on access)
    cameras: list[Camera]  # working pinhole camera per frame
    cam_from_world: np.ndarray  # (M, 4, 4)
    extracted: int | None = None  # frames extracted by this build (None: all; fewer from a feature cache)

    def without_state(self) -> SequenceABC[Features]:
        """The features without the sampling state where that saves reading (tracking needs none)."""
        f = self.features
        return f.without_state() if hasattr(f, "without_state") else f


@dataclass(frozen=True)
class ExtractorSpec:
    """A picklable recipe for an extractor (tasks on other processes or machines make their own)."""

    name: str
    max_keypoints: int = 2048

    def create(self, device: str | None = None) -> Extractor:
        """The extractor on ``device`` (None or "cpu": the CPU)."""
        return _cached_extractor(self.name, self.max_keypoints, None if device in (None, "cpu") else device)

    @property
    def uses_device(self) -> bool:
        """Whether the extractor runs on a torch device (a GPU helps)."""
        return bool(getattr(feats_mod.extractor_class(self.name), "uses_device", False))

    @property
    def samples_on_device(self) -> bool:
        """Whether sampling descriptors (the training patches) can run on a GPU (Extractor.samples_on_device)."""
        return bool(getattr(feats_mod.extractor_class(self.name), "samples_on_device", False))


@lru_cache(maxsize=64)
def _cached_extractor(name: str, max_keypoints: int, device: str | None, thread: int = 0) -> Extractor:
    return feats_mod.create(name, max_keypoints=max_keypoints, device=device)


def _extractor(ex: Extractor | ExtractorSpec, device: str | None = None) -> Extractor:
    if not isinstance(ex, ExtractorSpec):
        return ex
    if ex.uses_device:  # a torch model: one per device, shared by threads (inference does not change it)
        return ex.create(device)
    # OpenCV's extractor objects: one per thread (LocalExecutor's pool), they are cheap to create
    on = None if device in (None, "cpu") else device  # SIFT on a GPU: its patch descriptors computed there
    return _cached_extractor(ex.name, ex.max_keypoints, on, threading.get_ident())


def _on_cpu(x):
    """Torch tensors in a (nested tuple/list/dataclass of) extractor state moved to the CPU, so that a
    result computed on a GPU worker can be read on a machine without one."""
    if isinstance(x, torch.Tensor):
        return x.cpu()
    if isinstance(x, (tuple, list)):
        return type(x)(_on_cpu(v) for v in x)
    if is_dataclass(x) and not isinstance(x, type):
        return replace(x, **{f.name: _on_cpu(getattr(x, f.name)) for f in fields(x) if f.init})
    return x


@dataclass
class ExtractTask:
    """One frame to extract: the image file's bytes (workers need no access to the sequence)."""

    name: str  # the image path, for messages
    data: bytes
    camera: Camera
    max_side: int
    extractor: Extractor | ExtractorSpec
    keep_image: bool = False


@dataclass
class ExtractedFrame:
    features: Features
    camera: Camera  # working pinhole camera
    image: np.ndarray | None = None  # the working image, when asked for


def extract_frame(task: ExtractTask, device: str | None = None, report=None) -> ExtractedFrame:
    img, cam = decode_and_prepare(task.data, task.name, task.camera, task.max_side)
    f = _extractor(task.extractor, device).extract(img)
    if f.dense is not None:
        f.dense = _on_cpu(f.dense)
    return ExtractedFrame(f, cam, img if task.keep_image else None)


# sequences longer than this keep their features in a temporary on-disk cache (build_map's feature_cache)
MAP_CHUNK = 64  # tasks per executor.map call of a streamed stage (results held at once)


def map_into(executor: Executor, fn, tasks, total: int, sink, gpu: bool = False, progress=None, chunk: int = MAP_CHUNK):
    """``executor.map_each`` over ``tasks`` in chunks of ``chunk`` tasks, handing each result to
    ``sink(i, result)`` (in order): at most one chunk of results is ever held (none by an executor
    that hands each over as it completes)."""
    it = iter(tasks)
    done = 0
    while done < total:
        block = [t for _, t in zip(range(min(chunk, total - done)), it)]
        if not block:
            break
        off = done
        report = (lambda d, off=off: progress(off + d)) if progress else None
        executor.map_each(fn, block, len(block), lambda k, r, off=off: sink(off + k, r), gpu=gpu, progress=report)
        done += len(block)
        del block


def _image_key(path) -> str:
    return str(Path(path).resolve())


def extract_sequence(
    seq: Sequence,
    extractor: Extractor | ExtractorSpec,
    max_side: int,
    progress=None,
    keep_images: list | None = None,
    executor: Executor | None = None,
    cache: FeatureCache | None = None,
) -> FrameFeatures:
    """Features of every frame (one task per frame; the image bytes are read here, lazily).

    With ``cache``, each frame's features go to the cache as they arrive and the result reads them
    back from it on access (memory stays flat in the number of frames); images the cache already
    holds (same file size and time) are not extracted again."""
    executor = executor or LocalExecutor()
    gpu = isinstance(extractor, ExtractorSpec) and extractor.uses_device
    poses = np.stack([f.cam_from_world for f in seq.frames])
    if cache is None:
        todo = list(seq.frames)
    else:
        keys = [_image_key(fr.image_path) for fr in seq.frames]
        todo, stamps, seen = [], [], set()
        for fr, k in zip(seq.frames, keys):
            stamp = source_stamp(fr.image_path)  # before the bytes are read (a file changed meanwhile is redone)
            if k not in seen and not cache.has(k, stamp):
                todo.append(fr)
                stamps.append(stamp)
            seen.add(k)
    tasks = (
        ExtractTask(
            str(fr.image_path),
            read_image_bytes(fr.image_path),
            seq.cameras[fr.camera_id],
            max_side,
            extractor,
            keep_images is not None and cache is None,
        )
        for fr in todo
    )
    n = len(todo)
    results: list = []

    def sink(i, r: ExtractedFrame):
        if cache is None:
            results.append(r)
        else:
            cache.put(_image_key(todo[i].image_path), r.features, r.camera, stamps[i])

    report = (lambda d: progress("extract", int(d), n)) if progress else None
    map_into(executor, extract_frame, tasks, n, sink, gpu, report)
    if cache is None:
        if keep_images is not None:
            keep_images.extend(r.image for r in results)
        return FrameFeatures([r.features for r in results], [r.camera for r in results], poses)
    if keep_images is not None:  # (an observer that shows the images: decoded again, not cached)
        keep_images.extend(
            decode_and_prepare(None, fr.image_path, seq.cameras[fr.camera_id], max_side)[0] for fr in seq.frames
        )
    return FrameFeatures(cache.view(keys), [cache.camera(k) for k in keys], poses, extracted=n)
