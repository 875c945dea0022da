"""Extending a map with a new posed capture, without building it again.

``extend_map(map, sequence, out, config)`` adds the frames of ``sequence`` to the map at ``map``:

1. the new frames' features are extracted with the map's extractor settings (its provenance's build
   config) and tracked among themselves as a build tracks them (:func:`favormap.build.track_frames`);
2. every landmark visible from a new frame (in the image, within its trained distance range and within
   ``view_cone_deg`` of its viewing cone) takes the keypoint within ``match_radius_px`` of its projection
   (default: the epipolar limit of the map's tracking) whose descriptor is most similar to the landmark's
   (its mean descriptor, or the one its grids render towards the new camera), above ``min_similarity``;
   each keypoint goes to one landmark at most;
3. a new track with such a keypoint joins that landmark (its majority, if several); the landmarks that
   gained observations are triangulated again from all their observations (observations that no longer
   fit are dropped; a landmark whose new observations all fail keeps what it had), and the other new
   tracks are triangulated into new landmarks; the extended map keeps the landmarks a build would keep
   within its landmark budget (``max_landmarks``: the longest tracks, grown ones counted as grown, among
   the map's landmarks and the new ones, then the best remaining tracks of frames that see fewer than the
   map's ``min_frame_landmarks``), so it holds as many landmarks as a build of all its frames;
4. a grown landmark whose grids already render what the new frames saw of it (each new observation's
   keypoint descriptor as close to the rendering towards its frame as the landmark's training patches were
   to theirs) keeps them; the other grown landmarks' grids are fine-tuned and the new landmarks' trained, in
   one training (:func:`favormap.voxels.batches.train_batches`, the map's voxel settings): a grown landmark trains on
   the patches of its new observations, sampled from the new frames, and on those of its existing
   observations as its current grids render them (the rays of the existing frames' patch pixels), and Adam
   starts from its current grids; so the mapping images need not be at hand, and the result stays close
   to the current grids where the new frames add nothing;
5. frames, cameras, tracks, view cones, provenance and the datasets' checksums are written as a new map
   (atomically: :class:`favormap.mapfile.MapWriter`); the input map is never written to.

The stages live in modules of this package: :mod:`.matching` (step 2 and the attachment of
step 3), :mod:`.triangulate` (3) and :mod:`.budget` (its landmark budget; the choice of the landmarks to
retrain), :mod:`.training` (4), :mod:`.frames` and :mod:`.assemble` (5), :mod:`.grids` (the map's grids read and
rendered); :mod:`.pipeline` runs them in order, each stage a function from a typed input to a typed output
(:class:`.matching.NewFrames`, :class:`.matching.Attachment`, :class:`.triangulate.Grown`,
:class:`.training.Trained`, :class:`favormap.mapfile.model.MapData`); :mod:`.api` holds :func:`extend_map`.
"""

from ..extend_config import ExtendConfig
from .api import ExtendSummary, extend_map, map_build_config, moved_sequence
from .budget import unexplained, within_budget
from .frames import frames_in_map
from .matching import attach_tracks, match_landmarks, match_radius

__all__ = [
    "ExtendConfig",
    "ExtendSummary",
    "attach_tracks",
    "extend_map",
    "frames_in_map",
    "map_build_config",
    "match_landmarks",
    "match_radius",
    "moved_sequence",
    "unexplained",
    "within_budget",
]
