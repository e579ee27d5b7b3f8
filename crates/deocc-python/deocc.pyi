"""Fast generative scene de-occlusion for vision and robotics (the deocc Rust library).

Frames are dicts of numpy arrays; every call checks its input and raises ValueError naming the
frame and the field. The GIL is released while the pipeline, the planners and the client run.
"""

from typing import Any, Dict, List, Optional, Sequence, Tuple, TypedDict, Union

import numpy as np
import numpy.typing as npt

__version__: str

class Frame(TypedDict, total=False):
    rgb: npt.NDArray[np.uint8]
    """(H, W, 3) RGB."""
    depth: Union[npt.NDArray[np.uint16], npt.NDArray[np.float32]]
    """(H, W) depth: uint16 millimetres or float32 metres (REP-118); 0 or NaN = no measurement."""
    K: Sequence[Sequence[float]]
    """3x3 intrinsics: fx 0 cx / 0 fy cy / 0 0 1."""
    distortion_model: str
    """Optional lens model as ROS names it: plumb_bob, rational_polynomial or equidistant."""
    D: Sequence[float]
    """Its coefficients in ROS order; the images are undistorted on arrival (same K)."""
    pose: Sequence[Sequence[float]]
    """Optional 4x4 world-from-camera pose (OpenCV axes); every frame or none."""
    instances: npt.NDArray[np.uint16]
    """Optional (H, W) instance ids, consistent across frames, 0 = background."""
    name: str

class Cloud(TypedDict):
    points: npt.NDArray[np.float32]
    """(N, 3) world frame, metres."""
    colors: npt.NDArray[np.uint8]
    """(N, 3) RGB."""
    instance: npt.NDArray[np.uint32]
    """(N,) instance id, 0 = background."""
    provenance: npt.NDArray[np.uint8]
    """(N,) 0 observed, 1 GL-DoT, 2 plane fill, 3 rules completer."""
    confidence: npt.NDArray[np.float32]
    """(N,) 1 observed; generated: the completer's probability that the point's pixel belongs
    to the object (0.5 for the support and plane fills, which measure none)."""

class Result(Cloud):
    observed: Cloud
    report: Dict[str, Any]
    """The run report (report.json of `deocc run`)."""

class Grasp(TypedDict):
    position: List[float]
    rotation: List[List[float]]
    width: float
    score: float

class PlaceMap(TypedDict):
    plane_height: float
    bounds: List[float]
    cell_m: float
    placeable: npt.NDArray[np.bool_]
    """(ny, nx) cells where the footprint's centre may go."""

class Placement(TypedDict, total=False):
    found: bool
    position: List[float]
    clearance_m: float
    score: float
    plane: int
    maps: List[PlaceMap]

def run(
    frames: List[Frame],
    options: Optional[Union[Dict[str, Any], str]] = None,
    completer: str = "gldot,rules",
    weights: Optional[str] = None,
    segment: bool = False,
    structure_ids: Optional[List[int]] = None,
) -> Result:
    """The pipeline: completes the occluded objects and fuses them into the cloud.

    options: pipeline options (the fields of `deocc run --options`); completer: "gldot",
    "rules" or a chain, default "gldot,rules" as `deocc run`; weights: a model folder (default the built-in model);
    segment: ignore given instance maps and segment every frame. To fill the depth the sensor
    did not measure first (small holes, from their measured neighbours): options
    {"fill_depth_max_gap_px": 8}; the report's "depth_fill" says what was filled per frame.
    """

def read_scene(path: str) -> Tuple[List[Frame], List[int]]:
    """A scene folder as `deocc run` reads it: (frames, structure_ids)."""

def read_ply(path: str) -> Cloud:
    """A PLY written by deocc (completed.ply, observed.ply)."""

def grasp(
    points: npt.NDArray[np.float32],
    instance: npt.NDArray[np.uint32],
    target: int,
    options: Optional[Union[Dict[str, Any], str]] = None,
) -> List[Grasp]:
    """Antipodal grasps on instance `target`, best first, checked against every point."""

def target_at(
    points: npt.NDArray[np.float32],
    instance: npt.NDArray[np.uint32],
    pixel: Sequence[float],
    camera: Dict[str, Any],
) -> int:
    """The instance seen at pixel (u, v) or filling box (u0, v0, u1, v1) of a view.

    `camera`: K (3x3), width, height, and optionally pose (4x4 world from camera),
    distortion_model and D (then pixels are of the image as the camera gave it)."""

def placing_options() -> Dict[str, Any]:
    """Pipeline options with every far side thin, for `run(options=...)`: more free table on
    clean depth, more false free space under a real sensor (`deocc place` keeps the defaults)."""

def place(
    points: npt.NDArray[np.float32],
    footprint: Tuple[float, float] = (0.08, 0.08),
    height: float = 0.12,
    up: Tuple[float, float, float] = (0.0, 0.0, 1.0),
    robot: Tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> Placement:
    """Where an object of this footprint and height can be put down."""

class Client:
    """A client of `deocc serve`."""

    def __init__(self, address: str = "http://127.0.0.1:50051", token: Optional[str] = None) -> None: ...
    def health(self) -> Dict[str, Any]: ...
    def complete(
        self,
        frames: List[Frame],
        options: Optional[Union[Dict[str, Any], str]] = None,
        segment: bool = False,
        timeout_s: Optional[float] = None,
    ) -> Result:
        """`run` on the server; raises ValueError for a request the server calls invalid."""
