"""The tracker stage's settings: the structure tracker's (:class:`~cadalign.infer.track.tracker.StructureTracker`),
the movable parts' and the stage's (:func:`~cadalign.infer.track.run.track_video`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from cadalign.infer.track.acquire import AcquireConfig
from cadalign.infer.track.edges import EdgeLevel, EdgeTrackConfig, with_levels
from cadalign.infer.track.flow import FlowConfig
from cadalign.infer.track.survey import SurveyConfig


@dataclass(frozen=True)
class TrackerConfig:
    """The structure tracker (see the module doc)."""

    edges: EdgeTrackConfig = field(default_factory=EdgeTrackConfig)
    """Per-frame correction against contours, coarse to fine."""
    acquire: AcquireConfig = field(default_factory=AcquireConfig)
    """The pan/tilt/roll search around a restart hypothesis (a rough pose)."""
    flow: FlowConfig = field(default_factory=FlowConfig)
    """The prediction from sparse flow since the last tracked frame (model-based visual odometry)."""
    learn_every: int = 1
    """The parts' colours are learned on every this many tracked frames (and on any while none are known); the fast
    preset's 2 saves about 3 ms a frame (docs/tuning/tracker.md#fewer-colour-lessons-and-a-shorter-lucas-kanade-s57)."""
    restart_levels: tuple[EdgeLevel, ...] = (
        EdgeLevel(0.125, 8, 4.0, 3.0),
        EdgeLevel(0.25, 8, 6.0, 4.0),
        EdgeLevel(0.5, 4, 4.0, 2.5),
        EdgeLevel(1.0, 3, 2.5, 1.5),
    )
    """The contour fit of a restart hypothesis: a wider basin than a tracked frame's (a 1/8 level, more rounds)."""
    restart_fit_step: int = 1
    """A restart's fit fits every this many contour samples, whatever ``edges.fit_step`` (a start decides the track;
    fast's 2 left turbid starts 0.5 m off or lost: docs/tuning/tracker.md#starts-fit-every-sample-s59)."""
    flow_levels: tuple[EdgeLevel, ...] | None = None
    """The contour fit of a frame the flow predicted; None: the same levels as any frame. The fast preset fits such a
    frame at full resolution only (docs/tuning/tracker.md#trackerconfigflow_levels, #carried-contours-s56)."""
    steady_heading: bool = True
    """When the constant-velocity prediction fails, also try the last step's translation (in the camera's frame
    and in the world's) with the last orientation: a survey ROV's heading jitters while its track holds
    (docs/tuning/tracker.md#prediction-and-turns)."""
    orbit_step_deg: float = 30.0
    """While lost, with nothing else to restart from, the last view is also tried turned round the structure's
    vertical axis (world z) in steps of this many degrees (a cut to another side of the structure); 0: off."""
    orbit_fits: int = 3
    """Of those turned views, the best this many by the search's score are fitted."""
    orbit_every: int = 4
    """The turned views are tried on the first lost frame and every this many after (about 10 s of CPU each on
    the default orbit): a return is regained within this many frames."""
    turn_step_deg: float = 30.0
    """While lost, the camera carried on at its last step is also tried turned on the spot about the world
    vertical in steps of this many degrees (an ROV turning at a survey line's end out of the structure's view);
    0: off. The best ``orbit_fits`` by the search's score are fitted (docs/tuning/tracker.md#prediction-and-turns)."""
    turn_frames: int = 4
    """... on each of the first this many lost frames (dead reckoning drifts by about a step each frame)."""
    survey: SurveyConfig = field(default_factory=SurveyConfig)
    """While lost and after the turned views, the last view's height, tilt and roll searched over the whole ground
    at any heading, ranked by the learned colours (:mod:`cadalign.infer.track.survey`)."""
    own_turn_limit: bool = True
    """Refuse a restart from the tracker's own hypotheses (dead reckoning, turned views) whose fit turned the
    camera further from the hypothesis than one pan/tilt search reaches: on the turbid survey right restarts
    turned 4-7 deg, wrong ones 17-89 (docs/tuning/tracker.md#prediction-and-turns)."""
    track_turn_deg: float = 15.0
    """A tracked frame's fit that turned the camera further than this from its prediction ran off onto other edges
    and is refused, degrees (0: off): right ones turned at most 9 deg on eight captures, a lattice's corner seen
    alone 64 (docs/tuning/tracker.md#tracked-frames-that-turn-s57)."""
    unique_margin: float = 0.05
    """A restart from the tracker's own hypotheses (no navigation pose) is taken only when the view turned by quarter
    turns round the structure's vertical ranks this much lower (:meth:`StructureTracker.rank`): a lattice fits
    itself turned (docs/tuning/tracker.md#ambiguous-restarts); 0: off."""
    rank_min_samples: int = 30
    """Contour samples a part needs to count in :meth:`StructureTracker.rank`."""
    start_margin: float = 0.05
    """A restart hypothesis' own fit is kept unless a candidate of the search round it has this much more
    support (on a cluttered desk, wrong candidates reached the right pose's support)."""
    start_climbs: int = 3
    """A start (no track yet) searches round its best fit again up to this many times while the support rises by more
    than ``climb_gain`` (docs/tuning/tracker.md#starts-that-climb-s59)."""
    climb_gain: float = 0.01
    """See ``start_climbs``: a share of the contour samples."""
    polish_start: bool = True
    """Fit a start again once the parts' colours are learned at it, and keep it when its support is ``start_margin``
    higher (a start 2 deg / 0.3 m off reached 0.06 deg: docs/tuning/tracker.md#starts-fitted-again-with-colours-s60)."""
    acquire_rounds: int = 2
    """Searches per hypothesis: when none of a search's candidates passes, the next searches round the best of
    them (a rough pose whose error is partly translation needs two)."""
    velocity: float = 1.0
    """Share of the last frame-to-frame motion carried into the prediction (0: the last pose; 1: constant
    velocity, as a survey ROV flies)."""
    min_support: float = 0.35
    """Lost below this share of contour samples with an image edge (see ``EdgeTrackConfig.support_px``), in any water: a
    floor under the right poses of turbid water
    (docs/tuning/tracker.md#how-the-thresholds-were-chosen-and-what-they-were-chosen-on)."""
    min_start_support: float = 0.45
    """A restart hypothesis is taken only with at least this support (and the best-supported one wins)."""
    relative_support: float = 0.7
    """Lost below this share of the track's recent median support (a drop, where the absolute level depends on
    the water and the structure)."""
    doubt_support: float = 0.9
    """A tracked frame whose support is below this share of the track's recent median is checked against the
    pan/tilt/roll search round its prediction, and the better-supported pose is kept."""
    history: int = 10
    """Tracked frames whose median support ``relative_support`` refers to."""
    min_samples: int = 150
    """Lost when the CAD shows fewer contour samples at the pose (the structure left the view)."""
    min_region_support: float = 0.2
    """Once the parts' colours are learned, lost below this share of contour samples on a colour boundary
    (``EdgeFit.region_support``)."""
    relative_region: float = 0.7
    """... or below this share of the recent tracked frames' region support. Unlike the edge support's, this
    history outlives a loss: a restart must look like the parts did (on visp_rbt a restart onto a wrong pose had
    edge support 0.53 and region support 0.01, right poses 0.75-0.81)."""
    max_residual_region_px: float = 1.0
    """The residual allowed when the region term confirms the pose (colours learned, region support passing):
    motion blur smears a hand-held frame's edges by a pixel (visp_rbt's blurred frames: 0.75-0.87 px at right
    poses)."""
    max_residual_px: float = 0.7
    """Lost when the supported samples' median offset exceeds this, pixels (a pose near but off the edges)."""
    nav_max_deg: float = 25.0
    """With a navigation pose per frame (``infer --nav``): a pose turned further than this from the frame's
    navigation pose is refused, degrees: 2.5 times a rough fix's 10 deg (room for the track's own error), far below
    the 90 deg of a lattice frame's symmetric fits (docs/tuning/tracker.md#navigation-per-frame)."""
    nav_max_m: float = 2.5
    """... or whose camera centre is further than this from the navigation pose's, metres (a rough fix is good
    to ~0.5 m; the symmetric fits of the turbid survey were 3.5-9 m off)."""


def _part_tracker() -> TrackerConfig:
    return TrackerConfig(edges=EdgeTrackConfig(prior_px=1.0), acquire=AcquireConfig(max_turn_deg=4.0, max_roll_deg=5.0),
                         min_samples=30, orbit_step_deg=0.0, turn_step_deg=0.0, unique_margin=0.0,
                         survey=SurveyConfig(every=0))


@dataclass(frozen=True)
class MovableConfig:
    """How movable parts are tracked."""

    tracker: TrackerConfig = field(default_factory=_part_tracker)
    """Each part's tracker: the structure's with a prior on each correction (a lone part's few contours leave
    directions unfixed), fewer samples needed, a 4 deg start search, no turned views and no test of them (a part's
    symmetry is declared; docs/tuning/tracker.md#movable-parts)."""


@dataclass(frozen=True)
class TrackRunConfig:
    """The tracker stage: the tracker and what is reported of each part."""

    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    max_width: int = 640
    """Frames wider than this are tracked at this width (area-averaged, intrinsics scaled), pixels; 0: at their own.
    The tracker's pixel tolerances were chosen at 640x480; at 1280x960 a start locked 1 m off and tracking took 4x
    the time (docs/tuning/tracker.md#working-resolution-s55). poses.jsonl keeps the frame's pixels."""
    min_visible_px: int = 4
    """A part is reported in a tracked frame when at least this many of its pixels are visible at the pose."""
    min_part_samples: int = 30
    """A part with at least this many contour samples is checked for support (fewer: too little to judge)."""
    min_part_support: float = 0.05
    """A checked part whose contour samples find image edges less often than this is reported missing (not
    where the CAD puts it), not placed."""
    min_part_concentration: float = 0.0
    """A checked part whose found edges lie near its outline less often than this (see
    :attr:`~cadalign.infer.track.edges.EdgeFit.instance_support`) is reported missing: near edges of texture or
    clutter where the part should be do not make it present."""
    min_part_region: float = 0.02
    """Once the parts' colours are learned, a part (with ``min_region_samples``) whose contour samples find their colour
    boundary less often than this, and image edges less often than ``missing_part_edges``, is reported missing: an
    absent part's outline separates no colours (docs/tuning/tracker.md#missing-parts)."""
    missing_part_edges: float = 0.6
    """See ``min_part_region``: a part whose outline finds image edges this often is not called missing."""
    present_part_region: float = 0.1
    """A part found missing stays missing until a check gives it at least this region support (in frames where
    it has fewer than ``min_region_samples`` it keeps its verdict)."""
    min_region_samples: int = 20
    """Contour samples a part needs for the region check."""
    min_hidden_samples: int = 10
    """A part hiding at least this many of the structure's contour samples (cast at half resolution), of which the
    image shows few (``hidden_seen``), is present whatever its own edges and colours (:mod:`.hidden`)."""
    hidden_seen: float = 0.5
    """... few: edges at fewer than this share of the frame's edge support (absent parts showed 0.57-1.4 of it, faint
    present ones 0-0.39: docs/tuning/tracker.md#the-contours-a-part-hides-s53)."""
    absent_seen: float = 0.85
    """A part is missing when the structure's contours it hides deep inside its outline (:class:`.hidden.HiddenSeen`),
    pooled over its last ``absent_checks`` frames, show image edges at this share of the frame's edge support or more
    (an absent valve: 0.96-1.34, present ones at most 0.75: docs/tuning/tracker.md#absent-small-parts-s54)."""
    absent_checks: int = 10
    """See ``absent_seen``: the frames pooled (those where the part hides deep samples)."""
    absent_samples: int = 20
    """See ``absent_seen``: the deep samples the pooled frames need for a verdict."""
    confirm_missing: int = 2
    """A part last found present is reported missing only after this many missing checks in a row; one check
    decides for a part never checked: an absent part is missing from frame 0 (docs/tuning/tracker.md#missing-parts)."""
    movable: MovableConfig = field(default_factory=MovableConfig)
    """Parts the scene declares movable, each tracked on its own (:mod:`cadalign.infer.track.parts`)."""
    overlay: bool = True
    """Write overlay.mp4."""
    overlay_fps: float = 5.0
    """Frames per second of overlay.mp4."""


PRESETS: dict[str, TrackRunConfig] = {
    # no 1/2 level, each round fits every 2nd contour sample, the full-resolution level fits the last judged render's
    # contours, the flow follows 200 corners (Lucas-Kanade stopping at 10 iterations or 0.03 px), a frame it predicted
    # is fitted at full resolution only, and the colours are learned on every second frame: 3 mm on the default orbit;
    # in turbid water it loses more frames (docs/tuning/tracker.md#a-faster-preset-s55, #carried-contours-s56,
    # #fewer-colour-lessons-and-a-shorter-lucas-kanade-s57)
    "fast": TrackRunConfig(TrackerConfig(edges=EdgeTrackConfig(levels=(EdgeLevel(0.25, 5, 6.0, 4.0),
                                                                       EdgeLevel(1.0, 3, 2.5, 1.5)), fit_step=2,
                                                               carry_deg=5.0),
                                         flow=FlowConfig(max_points=200, lk_iterations=10, lk_eps_px=0.03),
                                         learn_every=2,
                                         flow_levels=(EdgeLevel(1.0, 3, 2.5, 1.5),))),
    "balanced": TrackRunConfig(),
    "accurate": TrackRunConfig(TrackerConfig(edges=with_levels(EdgeTrackConfig(), iterations=6))),
}
"""``none`` is not a tracker preset; the CLI maps the detector pipeline's preset names onto these."""
