"""The knobs of map-to-map estimation (:class:`EstimateOptions`), apart from the code that reads them.

Both the search (:mod:`mapd.fusion.estimate`) and the judging of its candidates
(:mod:`mapd.fusion.judge`) read these options; they live here so that the estimator can import the
judge without the judge importing the estimator back.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class EstimateOptions:
    """Knobs of :func:`~mapd.fusion.estimate.estimate_transform`; the defaults are what ``mapd bench
    merge`` measures."""

    min_confidence: float = 0.5
    min_agreement: float = 0.8
    #: refuse pairs whose resolutions differ by more than this factor
    max_resolution_ratio: float = 4.0
    #: most cells of a map at the working resolution (2048 x 2048): a larger map is matched pooled
    #: to a coarser one. Matching costs a few hundred bytes a working cell (SIFT's pyramid, the
    #: orientation fields, the wall points), so a peer's 8192 x 8192 map (``limits.max_cells``)
    #: would otherwise take 16 GB and most of a minute; with the cap no map costs more than a
    #: 2048 x 2048 one
    max_match_cells: int = 1 << 22
    #: the correlation search works on images of about this many cells a side ...
    coarse_cells: int = 256
    #: ... with coarse cells no wider than this (meters)
    max_coarse_m: float = 0.4
    #: fewest wall cells a map needs before it is worth matching
    min_walls: int = 30
    #: overlapping wall cells at which the small-overlap discount ends ...
    support_walls: int = 150
    #: ... and free-space evidence (:attr:`mapd.fusion.refine.Score.free_evidence`) worth as much
    #: (about 6,500 cells known in both maps that agree, if none disagree); support adds the two,
    #: so an overlap whose free space disagrees more than it agrees loses support
    support_free: float = 50.0
    #: a candidate farther than this from the best (cells at b's centre, or degrees) is a rival
    rival_cells: float = 8.0
    rival_deg: float = 4.0
    use_features: bool = True
    #: try every heading when the signature and the features propose nothing acceptable
    exhaustive: bool = True
    #: candidates that get the full refinement and check, per search stage
    refine_top: int = 8
    #: walls that must pin the least constrained direction (see :func:`mapd.fusion.judge.confidence_factors`)
    constraint_walls: float = 6.0
    #: the per-wall ranking of correlation peaks counts at least this many walls (fine cells)
    coarse_floor: float = 150.0
    #: distinct correlation peaks proposed per ranking (signature headings; every heading)
    search_peaks: tuple[int, int] = (30, 30)
    #: a rival that fits worse is beaten when its wall evidence is short of the best's by more than
    #: twice max(first, second x the best's evidence) (see :func:`mapd.fusion.judge.distinct_by_evidence`)
    evidence_margin: tuple[float, float] = (30.0, 0.1)
    #: slide the best along its weakest direction to measure how well it is pinned down
    slide_test: bool = True
    #: peaks kept per ranking from each signature heading (and its +-3 degree neighbours), over the
    #: global best: in repetitive layouts other headings can crowd the true one out
    heading_peaks: int = 2
