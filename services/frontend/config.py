"""Frontend service configuration (defaults here; file, AISDF_* environment, command line)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import Field

from aisdf.config import Model, ServiceConfig
from aisdf.keyframes import KeyframeConfig


def _ros_domain_id() -> int:
    raw = os.environ.get("ROS_DOMAIN_ID", "").strip()
    return int(raw) if raw.isdigit() else 0


class Ros2SourceConfig(Model):
    """``--source ros2``: a live ROS 2 robot over rmw_zenoh (aisdf.ros.live)."""

    connect: list[str] = Field(default_factory=lambda: ["tcp/localhost:7447"],
                               description="Zenoh router(s) of the robot's ROS 2 network (rmw_zenoh's default)")
    zenoh_config: Path | None = Field(default_factory=lambda: Path(os.environ["ZENOH_SESSION_CONFIG_URI"])
                                      if os.environ.get("ZENOH_SESSION_CONFIG_URI") else None,
                                      description="Zenoh session file for the ROS side (default "
                                      "$ZENOH_SESSION_CONFIG_URI, as rmw_zenoh)")
    domain_id: int = Field(default_factory=_ros_domain_id, ge=0, le=232, description="ROS_DOMAIN_ID (default "
                           "$ROS_DOMAIN_ID or 0)")
    distro: Literal["humble", "iron", "jazzy", "kilted", "lyrical", "rolling"] = Field(
        "jazzy", description="message definitions, and the type hash in this node's own liveliness tokens")
    depth_topic: str = Field("/camera/depth/image_rect_raw", description="depth image topic")
    depth_type: Literal["image", "compressed"] = Field("image", description="sensor_msgs/Image or CompressedImage")
    info_topic: str = Field("/camera/depth/camera_info", description="sensor_msgs/CameraInfo topic")
    tf_topic: str = "/tf"
    tf_static_topic: str = "/tf_static"
    fixed_frame: str = Field("map", description="world frame of the poses (TF chain to the image's frame)")
    camera_frame: str | None = Field(None, description="camera frame instead of the images' header.frame_id")
    node_name: str = Field("aisdf_frontend", description="this ROS 2 node's name")
    idle_timeout_s: float | None = Field(None, gt=0, description="end after this long without a depth image "
                                         "(once one came); None: run until stopped")
    max_wait_s: float = Field(1.0, gt=0, description="an image waits this long at most for the TF to place it")
    tf_check: bool = Field(True, description="check the TF chain on the first frames (held meanwhile); refuse the "
                           "robot's frames in words when it fails (aisdf.ros.check)")
    tf_check_window: int = Field(90, ge=2, description="frames held and checked before mapping starts")
    odom_frame: str | None = Field(None, description="protocol 1.11: the odometry frame between fixed_frame and the "
                                   "camera; when map -> odom moves (a SLAM loop closure), the keyframes sent are "
                                   "re-posed in the map (aisdf.ros.follow; None: not followed)")
    follow_mode: Literal["stamp", "latest"] = Field("stamp", description="map -> odom at each keyframe's stamp "
                                                    "(stamp) or the newest one for every keyframe (latest)")
    follow_keyframes: int = Field(5000, ge=1, description="the newest this many keyframes sent are followed")
    follow_min_m: float = Field(0.01, ge=0, description="a keyframe is re-posed when its map -> odom moved more "
                                "than this (m) ...")
    follow_min_deg: float = Field(0.5, ge=0, description="... or turned more than this (degrees)")


class RosbagSourceConfig(Model):
    """``--source rosbag --path BAG``: a ROS 1 bag or rosbag2 recording (aisdf.ros.bag). Unset
    topics and frames are found in the recording when there is one obvious choice."""

    depth_topic: str | None = Field(None, description="depth image topic (sensor_msgs/Image or CompressedImage)")
    info_topic: str | None = Field(None, description="sensor_msgs/CameraInfo topic")
    fixed_frame: str | None = Field(None, description="world frame of the poses (default: the root of the TF tree "
                                    "holding the image's frame; with a pose topic, its header frame)")
    pose_topic: str | None = Field(None, description="PoseStamped/Odometry topic instead of /tf")
    camera_extrinsic: str | None = Field(None, description="with a pose topic: the camera's (optical frame's) pose "
                                         "in the pose's body frame: 'x y z qx qy qz qw', 'x y z yaw pitch roll', "
                                         "16 numbers, or 'optical [x y z]'; default identity")
    camera_frame: str | None = Field(None, description="camera frame instead of the images' header.frame_id")
    tf_check: bool = Field(True, description="check the TF chain on the first frames and refuse a recording that "
                           "fails (aisdf.ros.check)")


class FrontendConfig(ServiceConfig):
    """Settings of ``aisdf-frontend``."""

    source: str = Field("synthetic", description="synthetic, or a dataset kind (generic, 7scenes, tum, ...)")
    path: Path | None = Field(None, description="dataset folder, or the recording for rosbag (not for synthetic)")
    building: str = Field("office", description="synthetic building: office, manhattan, atlanta, stairs, floor (a multi-room floor), ...")
    change: Literal["cart", "person", "drift"] | None = Field(
        None, description="synthetic: a changing scene (aisdf.synthetic.changes): cart (a cart seen on a first pass "
        "of the walk, gone on the second), person (someone crossing the view), drift (poses drifting to 20 cm); "
        "n_frames is then one pass")
    change_pause_s: float = Field(10.0, ge=0, description="with change=cart or person: the pause between the "
                                  "walk's two passes (s)")
    seed: int = Field(0, description="synthetic building, trajectory and noise seed")
    n_frames: int = Field(900, ge=1, description="synthetic sequence length (frames)")
    width: int = Field(160, ge=8, description="synthetic image width")
    height: int = Field(120, ge=8, description="synthetic image height")
    noise: bool = Field(True, description="synthetic depth with the Kinect-like noise model")
    fps: float = Field(30.0, gt=0, description="sensor frame rate of the source")
    realtime: bool = Field(True, description="stream at the sensor's rate; false = as fast as possible")
    start: int = Field(0, ge=0, description="first frame index")
    stride: int = Field(1, ge=1, description="use every stride-th frame")
    max_frames: int | None = Field(None, ge=1, description="stop after this many frames")
    loop: bool = Field(False, description="start again at the end")
    linger: bool = Field(False, description="stay up (answering info/frontend) after the source ends")
    depth_encoding: Literal["f4", "u2"] = Field("f4", description="wire depth: f4 metres or u2 millimetres")
    sensor: str = Field("depth", description="sensor name put in every keyframe")
    keyframes: KeyframeConfig = Field(default_factory=KeyframeConfig)
    ros2: Ros2SourceConfig = Field(default_factory=Ros2SourceConfig)
    rosbag: RosbagSourceConfig = Field(default_factory=RosbagSourceConfig)
    reliable: bool = Field(True, description="wait for a mapper, resend until acknowledged (protocol 1.2); false: "
                           "publish each keyframe once (mappers before 1.2 send no acknowledgements)")
    hold_max: int = Field(128, ge=1, description="keyframes held unacknowledged (no mapper, or in flight); the "
                          "oldest is dropped beyond (logged, counted)")
    send_window: int = Field(8, ge=1, description="keyframes in flight (sent, not acknowledged) at most; keep it "
                             "below the mapper's queue_max")
    resend_period_s: float = Field(3.0, gt=0, description="a keyframe unacknowledged this long is sent again")
    drain_timeout_s: float = Field(60.0, ge=0, description="after the source ends, wait this long at most for "
                                   "the acknowledgements of what is held")
