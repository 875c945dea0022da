"""A query image's preparation and feature extraction, run on a worker thread while the localizer does other work.

:class:`QueryFeatures` holds one image's working image and camera (:meth:`Localizer.prepare`) and its features
(the extractor's), each available as soon as it is done: the localizer takes the camera first, to look up and
render the first iteration's landmarks from the prior, and the features when it needs them. A single query's
features are extracted beside that first rendering; a stream's next frame is prepared and extracted while the
current one is localized (:meth:`Localizer.localize_sequence`), so the extractor, which leaves part of the cores
idle, runs beside the whole of the localization, not only its start. Errors reach the caller where it takes what
failed, with their own type."""

from __future__ import annotations

import time
from concurrent.futures import Future

END = object()  # what a stream's image source gives past its last image


class QueryFeatures:
    """One query image's (working image, camera) and features, computed by :meth:`run` (on any thread)."""

    def __init__(self):
        self._prepared: Future = Future()
        self._features: Future = Future()
        self.seconds = 0.0  # preparing and extracting, on the thread that ran them

    def run(self, localizer, image, camera) -> None:
        """Prepare ``image`` for ``localizer`` and extract its features. ``image`` may be a callable that gives
        the image, or :data:`END` past a stream's last image (then :meth:`prepared` gives None)."""
        s = time.perf_counter()
        try:
            if callable(image):
                image = image()
            if image is END:
                self._prepared.set_result(None)
                return
            img, cam = localizer.prepare(image, camera)
        except BaseException as e:  # the caller sees it where it takes the image (or its features)
            self._prepared.set_exception(e)
            self._features.set_exception(e)
            return
        self._prepared.set_result((img, cam))
        try:
            feats = localizer.extractor.extract(img)
        except BaseException as e:
            self._features.set_exception(e)
            return
        self.seconds = time.perf_counter() - s
        self._features.set_result(feats)

    def prepared(self):
        """(working image, camera), or None past a stream's end; waits for them."""
        return self._prepared.result()

    def features(self):
        """The image's features; waits for them."""
        return self._features.result()
