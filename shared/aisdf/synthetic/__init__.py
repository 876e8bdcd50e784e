"""Built-in procedural indoor buildings with exact ground truth: scenes (exact SDF,
gradient and raycast in any world frame), camera trajectories, depth rendering with a
Kinect-v1-like noise model, and a lazily rendered posed depth sequence."""

from .buildings import BUILDINGS, PLANS, FloorPlan, make_building, random_world_frame
from .primitives import Boxes, Room
from .render import KinectNoise, nguyen_sigma, render_depth, render_depth_and_cos
from .scene import Scene
from .sequence import SyntheticSequence, pinhole_K
from .trajectory import make_trajectory, make_walk

__all__ = [
    "BUILDINGS", "Boxes", "FloorPlan", "KinectNoise", "PLANS", "Room", "Scene", "SyntheticSequence", "make_building",
    "make_trajectory", "make_walk", "nguyen_sigma", "pinhole_K", "random_world_frame", "render_depth",
    "render_depth_and_cos",
]
