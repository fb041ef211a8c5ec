"""Read-only queries of a COLMAP database with SQLite alone: counts, digests, names and ids.

pycolmap's open writes to the file even when only reading, which would change its bytes (and the
digests that decide whether a stage resumes), so what only reads goes through SQLite here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pycolmap

from ..io import LOW_SPACE_BYTES, DamagedOutputError, disk_full_error, fingerprint, free_bytes

_DB_TABLES = ("images", "keypoints", "descriptors", "matches", "two_view_geometries")


def _sqlite_header_problem(path: Path) -> str | None:
    """A database file shorter than its header says: truncated (None when it looks whole)."""
    import struct

    with open(path, "rb") as f:
        header = f.read(100)
    if len(header) < 100 or not header.startswith(b"SQLite format 3\x00"):
        return "not an SQLite database" if header else "empty file"
    page_size = struct.unpack(">H", header[16:18])[0]
    page_size = 65536 if page_size == 1 else page_size
    num_pages = struct.unpack(">I", header[28:32])[0]
    if header[92:96] == header[24:28] and path.stat().st_size < page_size * num_pages:
        return f"truncated: {path.stat().st_size} of {page_size * num_pages} bytes"
    return None


def _query(db_path: Path, *queries: tuple[str, tuple], modes: tuple[str, ...] = ("rw", "ro")) -> list[list[tuple]]:
    """Run read-only SQL on a database with SQLite alone (pycolmap's open writes to the file even
    when only reading, which would change its bytes). Opened read-write when possible, so that a
    write-ahead log is merged and removed on close; read-only in a read-only folder (and with
    `modes=("ro",)`, for a database that COLMAP is writing in another process)."""
    import sqlite3

    for mode in modes:
        try:
            con = sqlite3.connect(f"file:{db_path}?mode={mode}", uri=True)
            try:
                return [con.execute(sql, args).fetchall() for sql, args in queries]
            finally:
                con.close()
        except sqlite3.OperationalError as exc:
            # read-only too where read-write fails: a read-only folder, a full disk (SQLite then
            # says "disk I/O error" when it cannot make its journal)
            if mode == "ro" or not any(w in str(exc) for w in ("readonly", "read-only", "unable to open", "I/O")):
                raise
    raise AssertionError("unreachable")


def database_summary(db_path: Path) -> dict[str, Any] | None:
    """Counts and digests of a COLMAP database, read with SQLite alone (cheap; None when absent).

    num_images, num_images_with_keypoints, keypoints_digest (names and keypoint counts),
    num_matched_pairs, num_verified_pairs (two-view geometries with inliers), matches_digest
    (every pair's match and inlier counts and geometry type). Raises DamagedOutputError when the
    file is truncated or SQLite finds it malformed.
    """
    import sqlite3

    db_path = Path(db_path)
    if not db_path.is_file():
        return None
    problem = _sqlite_header_problem(db_path)
    if problem is not None:
        raise DamagedOutputError(f"{db_path} is damaged ({problem})")
    try:
        (tables,) = _query(db_path, ("SELECT name FROM sqlite_master WHERE type='table'", ()))
        missing = [t for t in _DB_TABLES if t not in {r[0] for r in tables}]
        if missing:
            raise DamagedOutputError(f"{db_path} is not a COLMAP database (no table {missing[0]})")
        images, keypoints, matches, geometries = _query(
            db_path, ("SELECT image_id, name FROM images ORDER BY image_id", ()),
            ("SELECT image_id, rows FROM keypoints ORDER BY image_id", ()),
            ("SELECT pair_id, rows FROM matches ORDER BY pair_id", ()),
            ("SELECT pair_id, rows, config FROM two_view_geometries ORDER BY pair_id", ()))
    except sqlite3.DatabaseError as exc:
        if free_bytes(db_path.parent) < LOW_SPACE_BYTES:  # a full disk, not a damaged file
            raise disk_full_error(db_path.parent) from None
        raise DamagedOutputError(f"{db_path} is damaged ({exc})") from None
    names = dict(images)
    return {
        "num_images": len(images),
        "num_images_with_keypoints": sum(1 for _, rows in keypoints if rows > 0),
        "keypoints_digest": fingerprint([(names.get(i, str(i)), rows) for i, rows in keypoints]),
        "num_matched_pairs": sum(1 for _, rows in matches if rows > 0),
        "num_verified_pairs": sum(1 for _, rows, _ in geometries if rows > 0),
        "matches_digest": fingerprint([matches, geometries]),
    }


def verified_graph(db_path: Path, min_num_inliers: int) -> tuple[int, int, list[int], int]:
    """(pairs with at least `min_num_inliers` verified matches, images they touch, the sizes of the
    connected groups of images they form (largest first), the most inlier matches of one pair):
    why a mapper may find no model."""
    (rows,) = _query(db_path, ("SELECT pair_id, rows FROM two_view_geometries WHERE rows >= ?",
                               (int(min_num_inliers),)))
    parent: dict[int, int] = {}

    def find(i: int) -> int:
        while parent.setdefault(i, i) != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for pair_id, _ in rows:
        i, j = pycolmap.pair_id_to_image_pair(int(pair_id))
        parent[find(int(i))] = find(int(j))
    groups: dict[int, int] = {}
    for i in list(parent):
        groups[find(i)] = groups.get(find(i), 0) + 1
    return len(rows), len(parent), sorted(groups.values(), reverse=True), max((int(r) for _, r in rows), default=0)


def verified_inliers(db_path: Path, min_num_inliers: int) -> dict[tuple[str, str], int]:
    """Verified inlier matches of each pair with at least `min_num_inliers`, keyed by the two image
    names in sorted order (read with SQLite: the file is not touched)."""
    return _counts_by_pair(db_path, "SELECT pair_id, rows FROM two_view_geometries WHERE rows >= ?",
                           (int(min_num_inliers),))


def match_counts(db_path: Path) -> dict[tuple[str, str], int]:
    """Matches (before geometric verification) of each matched pair, keyed by the two image names
    in sorted order (read with SQLite)."""
    return _counts_by_pair(db_path, "SELECT pair_id, rows FROM matches", ())


def _counts_by_pair(db_path: Path, sql: str, args: tuple) -> dict[tuple[str, str], int]:
    """(pair_id, count) rows of `sql` keyed by the pair's two image names in sorted order."""
    (rows, images) = _query(db_path, (sql, args), ("SELECT image_id, name FROM images", ()))
    name = {int(i): n for i, n in images}
    out: dict[tuple[str, str], int] = {}
    for pair_id, count in rows:
        i, j = (int(k) for k in pycolmap.pair_id_to_image_pair(int(pair_id)))
        if i in name and j in name:
            a, b = sorted((name[i], name[j]))
            out[(a, b)] = int(count or 0)
    return out


def images_with_keypoints(db_path: Path) -> set[str]:
    """Names of the images that have a keypoints entry (read with SQLite: the file is not touched)."""
    (rows,) = _query(db_path, ("SELECT name FROM images JOIN keypoints USING (image_id)", ()))
    return {name for (name,) in rows}


def database_images(db_path: Path) -> dict[str, int]:
    """name -> image_id of the images in a database (read with SQLite: the file is not touched)."""
    (rows,) = _query(db_path, ("SELECT name, image_id FROM images", ()))
    return {name: int(image_id) for name, image_id in rows}


def camera_models(db_path: Path) -> dict[int, tuple[int, bool]]:
    """camera_id -> (COLMAP's model id, whether its focal length is a prior): read-only."""
    (rows,) = _query(db_path, ("SELECT camera_id, model, prior_focal_length FROM cameras", ()), modes=("ro",))
    return {int(camera_id): (int(model), bool(prior)) for camera_id, model, prior in rows}


def camera_priors(db_path: Path) -> dict[int, bool]:
    """camera_id -> whether its focal length came with the images (EXIF): read-only, also while
    COLMAP writes the database in another process."""
    return {camera_id: prior for camera_id, (_, prior) in camera_models(db_path).items()}
