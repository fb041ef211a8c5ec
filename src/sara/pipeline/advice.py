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
                 "files, the true intrinsics all 47 each time); if you do not, sara holds the lens distortion while "
                 "mapping (map.hold_distortion_starved; -s map.refine_distortion=false holds it in the refinements "
                 "too)")
    return text


def starved(extract_info: dict[str, Any], backend: str) -> bool:
    """Whether SIFT starved on these images (`low_texture`) and some camera's focal length is a guess
    (neither EXIF nor camera_params gave it: `cameras_guessed` in the extract record)."""
    guessed, _ = extract_info.get("cameras_guessed") or (0, 0)
    return bool(low_texture(extract_info, backend)) and guessed > 0


def guessed_cameras(extract_info: dict[str, Any]) -> str:
    """A warning when the images have cameras of their own (they differ in size or EXIF camera) and
    most of those have no EXIF focal length: each then starts from COLMAP's guess, and where the
    photos were cropped or zoomed that guess is wrong for each in its own way (empty otherwise)."""
    guessed, cameras = extract_info.get("cameras_guessed") or (0, 0)
    if cameras < 2 or 2 * guessed <= cameras or extract_info.get("camera_mode") in ("per_video", "per_sequence"):
        return ""  # a camera per clip: its frames refine its one guess (and the focal check tests it)
    return (f"{guessed} of the {cameras} cameras (one per image: the images differ in size or EXIF camera) have no "
            "EXIF focal length: each starts from a guess, 1.2 times its image's longer side. If the photos were "
            "cropped or zoomed, that guess is wrong for each in its own way and no pair source gives good poses (a "
            "stand-in of cropped photos: relative rotations 5-6 degrees off with every pair matched, and SARA, with "
            "fewer pairs per photo, worse): keep the photos' EXIF, or give one camera to images that share one")


def forward_guess(extract_info: dict[str, Any], map_info: dict[str, Any]) -> str:
    """Advice after mapping when the views move along their optical axes (the mapper could start
    only from such a pair: `forward_start` in the map record) and the intrinsics were not given:
    from such views bundle adjustment does not find the principal point (refining it there moved it
    further off), and its offset from the centre turns every translation direction (empty otherwise)."""
    if not map_info.get("forward_start") or (extract_info.get("settings") or {}).get("camera_params"):
        return ""
    return ("The views move along their optical axes (a drive, or a walk straight ahead): from such views bundle "
            "adjustment cannot find the camera's principal point, which stays at the image's centre, and its true "
            "offset from there turns every translation direction by about offset / focal length. If you know the "
            "intrinsics (a calibration, a rectified dataset's), give them: -s "
            "extract.camera_model=PINHOLE -s extract.camera_params=fx,fy,cx,cy (kitti-seq1, principal point 11 px off "
            "the centre: AUC@1 / @5 0.03 / 0.79 without, 0.68 / 0.94 with its calibration)")


def given(stages: dict[str, dict[str, Any]], backend: str) -> list[str]:
    """Every piece of advice a finished run gave (SIFT starved; cameras from guessed focal lengths;
    360-degree panoramas; views moving straight ahead without the intrinsics), from its stage records:
    what the console said, for the run's reports."""
    extract = stages.get("extract", {})
    return [text for text in (low_texture(extract, backend), guessed_cameras(extract), panoramas(extract),
                              forward_guess(extract, stages.get("map", {}))) if text]


def warn_low_texture(extract_info: dict[str, Any], backend: str) -> str:
    """Log `low_texture`'s warning (once per run) and return it."""
    text = low_texture(extract_info, backend)
    if text:
        logger.warning(text)
    return text


#: 360-degree cameras write equirectangular panoramas, twice as wide as high; smaller 2:1 images are rare
PANORAMA_MIN_HEIGHT = 500


def count_panoramas(sizes: dict[str, tuple[int, int]]) -> int:
    """How many of the images (name -> (width, height)) are shaped as a 360-degree panorama: 2:1 to a
    pixel, at least PANORAMA_MIN_HEIGHT high."""
    return sum(abs(w - 2 * h) <= 1 and h >= PANORAMA_MIN_HEIGHT for w, h in sizes.values())


def panoramas(extract_info: dict[str, Any]) -> str:
    """A warning when most images look like 360-degree panoramas (`panoramas` in the extract info,
    set by the run from the images' sizes): COLMAP's camera models cannot describe them."""
    found, total = extract_info.get("panoramas", 0), extract_info.get("num_images", 0)
    if not found or 2 * found < total:
        return ""
    return (f"{found} of the {total} images are twice as wide as high, as the equirectangular panoramas of a "
            "360-degree camera are: COLMAP's camera models (pinhole, with radial distortion) cannot describe such "
            "an image, and the model will be poor or split; cut each panorama into perspective views (the faces "
            "of a cube, or the camera's own export of flat views) and run sara on those")

