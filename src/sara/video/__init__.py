"""Video input: the frames of a video, or of a folder of videos, picked and written as PNG images so
that the pipeline runs on them as on any folder of images (`sara run capture.mp4 OUT`).

Frames are picked evenly in time: each video is cut into as many windows of consecutive frames as
frames are wanted, and one sharp frame of each window is kept (by the variance of the Laplacian of
its grey image: the frame nearest the window's middle among those nearly as sharp as the sharpest),
since motion blur is what spoils the frames of a hand-held capture. A frame's name says where it
comes from and sorts in time order: `<video stem>_f<frame index>.png`, the index counted from 0 in
the video. `OUT/.sara/video.json` records the videos (size and digest), the
settings and every picked frame (index, time, sharpness): a re-run with the same videos and
settings reuses the frames without decoding; where videos were added, taken away or replaced, the
frames of the others are kept; other settings, or no video in common, are refused.

`picking`: the windows, the sharp frame of each, finding and decoding the videos; `folder`: the
frames folder of a run and its record.
"""

from .folder import FRAMES_GT, RECORD, camera_groups, frames_for_run, frames_ground_truth, read_record, summary
from .picking import (
    DEFAULT_FRAMES,
    FLAT_CONTRAST,
    SHARP_ENOUGH,
    SHARPNESS_SIDE_PX,
    SPARSE_SPACING_S,
    VIDEO_EXTENSIONS,
    FrameSettings,
    decode_video,
    find_videos,
    frame_name,
    frame_scores,
    open_video,
    pick_sharp,
    pick_textured,
    window_bounds,
)

__all__ = ["DEFAULT_FRAMES", "FLAT_CONTRAST", "FRAMES_GT", "RECORD", "SHARPNESS_SIDE_PX", "SHARP_ENOUGH",
           "SPARSE_SPACING_S", "VIDEO_EXTENSIONS", "FrameSettings", "camera_groups", "decode_video", "find_videos",
           "frame_name", "frames_for_run", "frames_ground_truth", "frame_scores", "open_video", "pick_sharp",
           "pick_textured", "read_record", "summary", "window_bounds"]
