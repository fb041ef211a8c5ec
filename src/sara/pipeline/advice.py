"""Advice given before the long work starts, from what the earlier stages measured."""

from __future__ import annotations

import logging
from typing import Any

logger = logging.getLogger(__name__)

#: SIFT keypoints per image (mean) under which a capture counts as low-texture: the shared scenes
#: hold thousands per image; the turntables where SIFT split the model held about 250
LOW_TEXTURE_KEYPOINTS = 500


def low_texture(extract_info: dict[str, Any], backend: str) -> str:
    """A warning when SIFT starved on these images (empty when it did not, or for learned features); when
    the focal length is COLMAP's guess (no EXIF, sara's check not applied), the advice to give the camera's
    intrinsics: there the sparse graph does not survive a wrong camera, the principal point included
    (lab/notes/CAPTURES.md, sections 21-22)."""
    mean = float(extract_info.get("keypoints_mean") or 0.0)
    if backend != "sift" or not extract_info.get("num_images") or mean >= LOW_TEXTURE_KEYPOINTS:
        return ""
    text = (f"SIFT found {mean:.0f} keypoints per image on average (under {LOW_TEXTURE_KEYPOINTS}): a low-texture "
            "capture, where SIFT's pairs are few and weak and the model may split into pieces; learned features "
            "find more there: --preset aliked-lightglue (pip install 'sara[learned]')")
    focal = extract_info.get("focal")
    if isinstance(focal, dict) and not focal.get("applied"):
        text += (f". The camera is a guess (focal length {focal.get('prior_px', 0):.0f} px, principal point at the "
                 "centre: no EXIF, and the images did not tell the focal length): if you know the intrinsics, give "
                 "them with -s extract.camera_params=f,cx,cy,k (on a low-texture stand-in whose principal point is "
                 "9 px off the centre, the guess kept 14 to 47 of 47 views in the main model under four namings of its "
                 "files, the true intrinsics all 47 each time); if you do not, sara maps again with the lens "
                 "distortion held when the first model holds under half the views (there: all 47 views in one model "
                 "under each naming), and -s map.refine_distortion=false holds it from the start")
    return text


def guessed_cameras(extract_info: dict[str, Any]) -> str:
    """A warning when the images have cameras of their own (they differ in size or EXIF camera) and
    most of those have no EXIF focal length: each then starts from COLMAP's guess, and where the
    photos were cropped or zoomed that guess is wrong for each in its own way (empty otherwise)."""
    guessed, cameras = extract_info.get("cameras_guessed") or (0, 0)
    if cameras < 2 or 2 * guessed <= cameras:
        return ""
    return (f"{guessed} of the {cameras} cameras (one per image: the images differ in size or EXIF camera) have no "
            "EXIF focal length: each starts from a guess, 1.2 times its image's longer side. If the photos were "
            "cropped or zoomed, that guess is wrong for each in its own way and no pair source gives good poses (a "
            "stand-in of cropped photos: relative rotations 5-6 degrees off with every pair matched, and SARA, with "
            "fewer pairs per photo, worse): keep the photos' EXIF, or give one camera to images that share one")


def warn_low_texture(extract_info: dict[str, Any], backend: str) -> str:
    """Log `low_texture`'s warning (once per run) and return it."""
    text = low_texture(extract_info, backend)
    if text:
        logger.warning(text)
    return text
