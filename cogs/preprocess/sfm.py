"""Step 4: cameras and sparse points of the static scene.

**Structure from motion** (pycolmap, as measured in shared/FACTS.md). Frames are written as
PNGs with masks (``X.png`` -> ``X.png.png``, black = no features) that hide the person and
the object, so only the static scene is matched. One SIMPLE_PINHOLE camera shared by every
frame, its focal length fixed at the prior (hand-held phone clips are mostly rotation:
letting bundle adjustment refine the focal gives inconsistent fragments), exhaustive
matching for short clips (sequential matching of a nearly panoramic clip leaves too few
wide-baseline pairs: 33/40 frames in 6 fragments with 66 points on the shared clip, against
40/40 and ~2k points exhaustively), sequential beyond, relaxed initialisation (homography-dominated pairs accepted, small
triangulation angles allowed), watermark detection off.

**No mapping without parallax**: where every verified pair that could start the mapper is
explained by a homography that is a pure rotation (``rotations_only``: a camera on a
tripod), no initial pair can show the 2 degrees of triangulation angle the mapper asks
for, and COLMAP would spend minutes trying them all (6 on the 100-frame juggle clip's
4,950 pairs) to fail; the mapper is not run and the rotation-only fallback takes over. A
probe of the pairs among 12 frames spread over the clip (``probe_pairs``, ``fixed_camera``)
tells a tripod first, so its thousands of pairs are not even matched; otherwise the probe
is thrown away and every pair is matched as before.

**Rotation-only fallback**, used when most frames fail to register or the reconstruction
has no usable parallax (a tripod-like clip) and its rotations explain the background worse
(``background_residuals``): per consecutive-frame homography of the
background (RANSAC), the rotation ``K^-1 H K`` (projected to SO(3) with the Kabsch fit on
the inlier bearings), chained from frame 0. The camera centre is fixed; the scene's depth
and scale then come from the ground plane and the body's metric size (see
``proxy_points``).

Both return cameras in an arbitrary world; ``cogs.preprocess.pipeline`` moves them into the
metric, z-up world the body fit defines.
"""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numba import njit

log = logging.getLogger(__name__)


@dataclass
class SfmResult:
    K: np.ndarray  # [3, 3]
    world_to_camera: np.ndarray  # [T, 4, 4]
    registered: np.ndarray  # [T] bool: pose estimated (others interpolated)
    points_xyz: np.ndarray  # [P, 3]
    points_rgb: np.ndarray  # [P, 3] uint8
    method: str  # "colmap" | "rotation"
    stats: dict = field(default_factory=dict)

    def arrays(self) -> dict:
        return {
            "K": self.K,
            "world_to_camera": self.world_to_camera,
            "registered": self.registered,
            "points_xyz": self.points_xyz,
            "points_rgb": self.points_rgb,
        }

    @classmethod
    def from_arrays(cls, a: dict, method: str, stats: dict) -> "SfmResult":
        return cls(a["K"], a["world_to_camera"], a["registered"].astype(bool), a["points_xyz"], a["points_rgb"], method, stats)


def intrinsics(width: int, height: int, focal_px: float) -> np.ndarray:
    return np.array([[focal_px, 0.0, 0.5 * width], [0.0, focal_px, 0.5 * height], [0.0, 0.0, 1.0]])


def feature_mask(person: np.ndarray, obj: np.ndarray | None, dilate_px: int) -> np.ndarray:
    """[H, W] bool: True where features may be taken (the static scene)."""
    import cv2

    moving = person.copy()
    if obj is not None:
        moving |= obj
    if dilate_px > 0:
        k = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)
        moving = cv2.dilate(moving.astype(np.uint8), k) > 0
    return ~moving


# -- pycolmap -------------------------------------------------------------------------


def import_pycolmap():
    # FACTS: importing pycolmap before cv2/PIL makes a later PNG write abort the process.
    import cv2  # noqa: F401
    import PIL.Image  # noqa: F401

    from cogs.errors import UserError

    try:
        import pycolmap
    except ImportError as e:
        raise UserError(
            f"pycolmap is not installed ({e}); install the preprocessing extra: "
            'pip install -e ".[preprocess]" (see docs/preprocess.md)'
        ) from None
    return pycolmap


def image_pairs(n: int, matching: str = "exhaustive", overlap: int = 10) -> list[tuple[int, int]]:
    """Frame pairs (a, b), a < b, to match among ``n`` frames: every pair ("exhaustive"), or
    each frame with the ``overlap`` after it and those 2, 4, 8 ... 2^(overlap-1) after it
    ("sequential", COLMAP's sequential pairing with quadratic overlap)."""
    if matching == "exhaustive":
        return [(a, b) for a in range(n) for b in range(a + 1, n)]
    out = []
    for a in range(n):
        ahead = sorted({a + 1 + i for i in range(overlap)} | {a + (1 << i) for i in range(overlap)})
        out += [(a, b) for b in ahead if b < n]
    return out


@njit(cache=True, nogil=True)
def _fold_two_best(dots, i0, best_r, top_r, second_r, best_c, top_c, second_c):
    """Fold rows ``i0 ..`` of a product (``dots`` [n, M] float32) into the two largest
    entries each way, in place: each of those rows' largest entry, the first index of it
    (numpy's ``argmax``: a tie makes the second equal to the largest) and its second largest
    (-inf where there is none), written at ``i0 ..`` of ``best_r``, ``top_r``, ``second_r``;
    and each column's so far, updated in ``best_c``, ``top_c``, ``second_c`` (start them at
    0, -inf, -inf). Rows must come in order for the columns' first index."""
    n, M = dots.shape
    for ii in range(n):
        i = i0 + ii
        row = dots[ii]
        for j in range(M):  # branch-free, so that it can be vectorised
            v, t = row[j], top_c[j]
            up = v > t
            second_c[j] = max(second_c[j], min(t, v))
            top_c[j] = v if up else t
            best_c[j] = i if up else best_c[j]
        b, bj, sb = -np.inf, 0, -np.inf
        for j in range(M):
            v = row[j]
            if v > b:
                sb, b, bj = b, v, j
            elif v > sb:
                sb = v
        best_r[i], top_r[i], second_r[i] = bj, b, sb


def match_descriptors(d1: np.ndarray, d2: np.ndarray, max_ratio: float = 0.8, max_distance: float = 0.7,
                      block: int = 1 << 21) -> np.ndarray:
    """COLMAP's SIFT matching of uint8 descriptors [N, 128] and [M, 128] -> [K, 2] uint32
    index pairs: each descriptor's nearest neighbour by angle (descriptors are unit vectors
    scaled by 512) under ``max_distance`` radians and under ``max_ratio`` x the second
    nearest's angle, kept where the two are each other's nearest.

    Exact, so the same in every run: dot products of uint8 vectors are integers under
    2^24, which float32 holds exactly in any order of summation (COLMAP's own CPU matcher
    goes through faiss and gave other matches now and then). The same matches as COLMAP's
    brute-force matcher on all 4,371 pairs of the guitar clip. The product is taken
    ``block`` entries (8 MB) at a time, whole rows, and folded into the two nearest each way
    (``_fold_two_best``) while it is in the cache: a large product is never held whole, and
    two frames of 3,800 features match in 25 ms on two cores, of 8,192 in 120 ms
    (docs/experiments/2026-11-29-exact-matching-time.md: blocks of 256 rows at 8,192
    features, against 32-1,024; a product that fits is taken whole, since small blocks
    alternating with the BLAS threads cost more than they save there).
    """
    N, M = len(d1), len(d2)
    if N == 0 or M == 0:
        return np.zeros((0, 2), np.uint32)
    f1, f2t = d1.astype(np.float32), np.ascontiguousarray(d2.astype(np.float32).T)
    best_r, top_r, second_r = np.zeros(N, np.int64), np.empty(N, np.float32), np.empty(N, np.float32)
    best_c, top_c, second_c = np.zeros(M, np.int64), np.full(M, -np.inf, np.float32), np.full(M, -np.inf, np.float32)
    rows = max(1, block // M)
    buffer = np.empty((min(rows, N), M), np.float32)
    for i0 in range(0, N, rows):
        dots = buffer[: min(rows, N - i0)]
        np.matmul(f1[i0 : i0 + rows], f2t, out=dots)
        _fold_two_best(dots, i0, best_r, top_r, second_r, best_c, top_c, second_c)

    def passes(top, second):
        angle = np.arccos(np.clip(top / 512.0**2, -1.0, 1.0))
        return (angle <= max_distance) & (angle < max_ratio * np.arccos(np.clip(second / 512.0**2, -1.0, 1.0)))

    idx = np.arange(N)
    keep = passes(top_r, second_r) & passes(top_c, second_c)[best_r] & (best_c[best_r] == idx)
    return np.stack([idx[keep], best_r[keep]], 1).astype(np.uint32)


# ``K^-1 H K`` of a homography is a rotation (its singular values equal) exactly when the
# camera only turned. A camera that also moved by t in front of a plane at distance d
# gives ``R + t n^T / d``, whose singular values spread by about |t| / d, while the
# mapper's initial pair needs a 2-degree triangulation angle (0.035 rad, about |t| / d):
# a spread under 1 % is no such pair. Measured: the juggle clip (a fixed camera) 0.03 %
# median, 0.1 % at most over 4,950 pairs; the homography-explained pairs of the
# basketball, bottle and guitar clips 1.1-4.3 % median (they have calibrated pairs too).
ROTATION_SPREAD = 0.01
MAPPER_MIN_INLIERS = 50  # the mapper's init_min_num_inliers
# Incremental mapping from one seed can break a clip into pieces that another seed joins:
# on the guitar clip (94 frames at 384 px, the same matches) seed 0 left 14 models, the
# largest posing 48 frames (so the rotation-only fallback, and held-out full-frame PSNR
# about 2 dB under the guitar's earlier COLMAP cameras), seeds 1 and 2 posed all 94. The
# mapper runs again, up to this many seeds in all, only where a run poses too few frames
# (``run_colmap``'s ``enough``): elsewhere the cameras are those of the first seed, as before.
MAPPER_ATTEMPTS = 3


def rotations_only(geometries: list[tuple[str, int, np.ndarray]], K: np.ndarray, min_inliers: int = MAPPER_MIN_INLIERS,
                   spread: float = ROTATION_SPREAD) -> bool:
    """Whether no verified pair can start incremental mapping -> bool.

    ``geometries``: per verified pair (COLMAP's configuration name, inlier count, its
    homography [3, 3]). Pairs with fewer than ``min_inliers`` inliers cannot start it;
    every other one must be homography-explained (``PANORAMIC`` or
    ``PLANAR_OR_PANORAMIC``) by a pure rotation: ``K^-1 H K``'s singular values within
    ``spread`` of the middle one (``ROTATION_SPREAD``)."""
    Ki = np.linalg.inv(K)
    for config, inliers, H in geometries:
        if inliers < min_inliers:
            continue
        if config not in ("PANORAMIC", "PLANAR_OR_PANORAMIC"):
            return False
        sv = np.linalg.svd(Ki @ np.asarray(H, np.float64) @ K, compute_uv=False)
        if sv[1] <= 0 or max(abs(sv[0] / sv[1] - 1.0), abs(sv[2] / sv[1] - 1.0)) > spread:
            return False
    return True


def _verified_geometries(pycolmap, db: Path) -> list[tuple[str, int, np.ndarray]]:
    """(configuration name, inlier count, homography) of every verified pair in ``db``."""
    names = {int(v): k for k, v in pycolmap.TwoViewGeometryConfiguration.__members__.items()}
    database = pycolmap.Database.open(str(db))
    try:
        _, geometries = database.read_two_view_geometries()
        return [(names.get(int(g.config), str(g.config)), len(g.inlier_matches), np.asarray(g.H)) for g in geometries]
    finally:
        database.close()


# The probe: every pair among PROBE_FRAMES frames spread evenly over the clip (66 pairs,
# whatever its length; 1.3 % of a 100-frame clip's 4,950). A tripod clip is told from it
# when at least PROBE_STRONG of them could start the mapper (enough inliers: a clip matched
# too weakly is not judged on a sample) and every one that could is a pure rotation.
PROBE_FRAMES = 12
PROBE_STRONG = 0.5


def probe_pairs(T: int, pairs: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """The pairs of ``pairs`` among ``PROBE_FRAMES`` frames spread evenly over T -> a list
    (empty when that would be all of them, or none)."""
    spread = set(np.linspace(0, T - 1, min(T, PROBE_FRAMES)).round().astype(int).tolist())
    probe = [(a, b) for a, b in pairs if a in spread and b in spread]
    return probe if 0 < len(probe) < len(pairs) else []


def fixed_camera(geometries: list[tuple[str, int, np.ndarray]], n_pairs: int, K: np.ndarray) -> bool:
    """Whether the verified ``geometries`` of ``n_pairs`` probe pairs show a camera that
    only turns: at least ``PROBE_STRONG`` of the pairs strong enough to start the mapper,
    and each of those a pure rotation (``rotations_only``)."""
    strong = sum(1 for _, inliers, _ in geometries if inliers >= MAPPER_MIN_INLIERS)
    return strong >= PROBE_STRONG * n_pairs and rotations_only(geometries, K)


def _match_and_verify(pycolmap, db: Path, work_dir: Path, names: list[str], pairs: list[tuple[int, int]], matching: str,
                      overlap: int, verification, progress=None) -> None:
    """Match ``pairs`` of frames exactly (``match_descriptors``) into the database ``db``
    and verify them with COLMAP (``verification``: its two-view geometry options).

    Descriptors are read as the pairs need them (pairs come in order of their first frame),
    and only a frame's and its near neighbours' are kept: 570 frames of 8,192 would be
    600 MB."""
    database = pycolmap.Database.open(str(db))
    try:
        ids = {im.name: im.image_id for im in database.read_all_images()}
        kept: dict[int, np.ndarray] = {}

        def descriptors(i: int, keep: bool) -> np.ndarray:
            d = kept.get(i)
            if d is None:
                d = np.asarray(database.read_descriptors(ids[names[i]]).data)
                if keep:
                    kept[i] = d
            return d

        for k, (a, b) in enumerate(pairs):
            for i in [i for i in kept if i < a]:
                del kept[i]
            near = matching == "exhaustive" or b - a <= overlap
            database.write_matches(ids[names[a]], ids[names[b]], match_descriptors(descriptors(a, True), descriptors(b, near)))
            if progress and (k + 1) % 50 == 0:
                progress("matching", k + 1, len(pairs))
    finally:
        database.close()
    pairs_file = work_dir / "pairs.txt"
    pairs_file.write_text("".join(f"{names[a]} {names[b]}\n" for a, b in pairs))
    pycolmap.verify_matches(db, pairs_file, options=verification)


def run_colmap(
    images: np.ndarray,
    static_masks: np.ndarray,
    K: np.ndarray,
    work_dir: Path,
    overlap: int = 10,
    matching: str = "exhaustive",
    progress=None,
    seed: int = 0,
    enough: int = 0,
) -> tuple[dict[int, np.ndarray], np.ndarray, np.ndarray, dict]:
    """Incremental SfM on frames [T, H, W, 3] with feature masks [T, H, W] (True = usable).

    ``progress(phase, done, total)`` is called as work advances. ``seed`` seeds the
    two-view verification's RANSAC and the mapper, and features are extracted and bundles
    adjusted on one thread; features are matched exactly (``match_descriptors``) on the
    pairs ``image_pairs`` names, and COLMAP verifies them: the same frames give the same
    reconstruction, to the last digit. Where the largest model poses fewer than ``enough``
    frames, the mapper runs again from the same matches with the next seeds
    (``MAPPER_ATTEMPTS`` in all) and the model posing the most frames is kept (the first
    of equals). Returns (world_to_camera per registered frame index, points [P, 3],
    colours [P, 3] uint8, stats; ``stats["mapper_seeds"]`` the seeds tried,
    ``stats["mapper_posed"]`` the frames each one's largest model posed, the kept seed
    ``stats["mapper_seed"]``).
    """
    pycolmap = import_pycolmap()
    from PIL import Image

    # COLMAP and Ceres log every step (and benign solver warnings) to stderr; keep errors.
    pycolmap.logging.minloglevel = 2
    pycolmap.logging.stderrthreshold = 2
    work_dir = Path(work_dir)
    if work_dir.exists():
        shutil.rmtree(work_dir)
    img_dir, mask_dir, out_dir = work_dir / "images", work_dir / "masks", work_dir / "sparse"
    for d in (img_dir, mask_dir, out_dir):
        d.mkdir(parents=True)
    T = len(images)
    names = [f"{t:06d}.png" for t in range(T)]
    for t in range(T):
        Image.fromarray(images[t]).save(img_dir / names[t], compress_level=1)
        Image.fromarray(static_masks[t].astype(np.uint8) * 255).save(mask_dir / f"{names[t]}.png")
    db = work_dir / "database.db"
    f, cx, cy = K[0, 0], K[0, 2], K[1, 2]

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_PINHOLE"
    reader.camera_params = f"{f},{cx},{cy}"
    reader.mask_path = str(mask_dir)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    # One thread: with several, the same frames gave reconstructions of 1,901-3,089 points
    # with poses apart by the scene's size (40 synthetic frames, two processes side by side;
    # docs/experiments/2026-11-28-a-ball-on-a-shoe.md).
    extraction.num_threads = 1
    chunk = max(1, min(8, T // 5 or 1))
    for s in range(0, T, chunk):
        if s > 0:
            reader.existing_camera_id = 1  # one camera for every frame, also across calls
        pycolmap.extract_features(
            db, img_dir, image_names=names[s : s + chunk], camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu,
        )
        if progress:
            progress("features", min(T, s + chunk), T)

    verification = pycolmap.TwoViewGeometryOptions()
    verification.max_H_inlier_ratio = 0.99  # hand-held clips are nearly panoramic
    verification.detect_watermark = False
    verification.ransac.random_seed = seed  # -1 (the default) seeds each run differently
    # Matching is ours, COLMAP's verification: its CPU matcher (through faiss) gave other
    # matches for a few pairs in 3 of 35 runs of the same frames, and twice another
    # reconstruction (docs/experiments/2026-11-28-feet-seen-end-on.md).
    def not_mapped(reason: str):
        if progress:
            progress("matching", 1, 1)
            progress("mapping", T, T)
        return {}, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), {"n_models": 0, "mapping": f"skipped: {reason}"}

    pairs = image_pairs(T, matching, overlap)
    probe = probe_pairs(T, pairs)
    if probe:
        # A few pairs first: a camera on a tripod is told from them, and the thousands of
        # others need not be matched to learn that no pair has parallax.
        _match_and_verify(pycolmap, db, work_dir, names, probe, matching, overlap, verification)
        probed = _verified_geometries(pycolmap, db)
        if fixed_camera(probed, len(probe), K):
            log.info("the camera only turns on the spot in %d pairs spread over the clip: structure from motion is "
                     "not run", len(probe))
            return not_mapped(f"no pair with parallax among {len(probe)} probe pairs")
        database = pycolmap.Database.open(str(db))
        try:  # the full matching starts from an empty table, as without the probe
            database.clear_matches()
            database.clear_two_view_geometries()
        finally:
            database.close()
    _match_and_verify(pycolmap, db, work_dir, names, pairs, matching, overlap, verification, progress)
    if rotations_only(_verified_geometries(pycolmap, db), K):
        log.info("no frame pair can start structure from motion (each is a turn of the camera on the spot, or matched "
                 "too weakly): the mapper is not run")
        return not_mapped("no pair with parallax")
    if progress:
        progress("matching", 1, 1)

    tried, posed, largest = [], [], []  # per attempt: its seed, the frames its largest model posed, that model
    for attempt in range(MAPPER_ATTEMPTS):
        recs = _map(pycolmap, db, img_dir, out_dir / str(attempt), seed + attempt, T, progress)
        rec = max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None
        tried.append(seed + attempt)
        posed.append(0 if rec is None else rec.num_reg_images())
        largest.append((rec, len(recs)))
        if posed[-1] >= enough or attempt + 1 == MAPPER_ATTEMPTS:
            break
        log.info("structure from motion posed %d of %d frames with mapper seed %d: mapping again with seed %d",
                 posed[-1], T, seed + attempt, seed + attempt + 1)
    k = posed.index(max(posed))  # the first of equals
    rec, n_models = largest[k]
    if rec is None:
        return {}, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), {"n_models": 0, "mapper_seeds": tried, "mapper_posed": posed}
    poses: dict[int, np.ndarray] = {}
    for img in rec.images.values():
        if not img.has_pose:
            continue
        t = names.index(img.name)
        m = np.eye(4)
        m[:3] = img.cam_from_world().matrix()
        poses[t] = m
    xyz, rgb, err = [], [], []
    for p in rec.points3D.values():
        xyz.append(p.xyz)
        rgb.append(p.color)
        err.append(p.error)
    stats = {
        "n_models": n_models,
        "mapper_seed": tried[k],
        "mapper_seeds": tried,
        "mapper_posed": posed,
        "n_registered": len(poses),
        "n_points": len(xyz),
        "mean_reprojection_error_px": float(np.mean(err)) if err else None,
    }
    if progress:
        progress("mapping", T, T)
    return poses, np.asarray(xyz, np.float64).reshape(-1, 3), np.asarray(rgb, np.uint8).reshape(-1, 3), stats


def _map(pycolmap, db: Path, img_dir: Path, out_dir: Path, seed: int, T: int, progress) -> dict:
    """One run of COLMAP's incremental mapper on the matched database -> its models."""
    opts = pycolmap.IncrementalPipelineOptions()
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    opts.ignore_watermarks = True
    opts.random_seed = seed
    opts.num_threads = 1  # bundle adjustment on several threads sums in another order each run
    opts.min_model_size = 3
    opts.mapper.init_min_tri_angle = 2.0
    opts.mapper.init_min_num_inliers = MAPPER_MIN_INLIERS
    opts.mapper.filter_min_tri_angle = 0.5
    opts.triangulation.min_angle = 0.5
    out_dir.mkdir(parents=True, exist_ok=True)
    registered = [0]

    def on_image():
        registered[0] += 1
        if progress:
            progress("mapping", min(registered[0], T), T)

    return pycolmap.incremental_mapping(db, img_dir, out_dir, options=opts, next_image_callback=on_image)


# -- pose interpolation ---------------------------------------------------------------


def fill_unregistered(w2c: dict[int, np.ndarray], T: int) -> tuple[np.ndarray, np.ndarray]:
    """Poses for all T frames from the registered ones: SLERP rotation and linear centre
    between registered neighbours, the nearest pose held beyond the ends."""
    import torch

    from cogs.geometry.rotations import quat_to_rotmat, rotmat_to_quat, slerp

    known = sorted(w2c)
    out = np.zeros((T, 4, 4))
    reg = np.zeros(T, bool)
    if not known:
        out[:] = np.eye(4)
        return out, reg
    for t in range(T):
        if t in w2c:
            out[t] = w2c[t]
            reg[t] = True
            continue
        after = [k for k in known if k > t]
        before = [k for k in known if k < t]
        if not before or not after:
            out[t] = w2c[after[0] if not before else before[-1]]
            continue
        a, b = before[-1], after[0]
        u = (t - a) / (b - a)
        qa = rotmat_to_quat(torch.from_numpy(w2c[a][:3, :3]))
        qb = rotmat_to_quat(torch.from_numpy(w2c[b][:3, :3]))
        R = quat_to_rotmat(slerp(qa, qb, torch.tensor(u, dtype=torch.float64))).numpy()
        ca = -w2c[a][:3, :3].T @ w2c[a][:3, 3]
        cb = -w2c[b][:3, :3].T @ w2c[b][:3, 3]
        c = (1 - u) * ca + u * cb
        out[t] = np.eye(4)
        out[t, :3, :3] = R
        out[t, :3, 3] = -R @ c
    return out, reg


def parallax_ratio(w2c: np.ndarray, registered: np.ndarray, points: np.ndarray) -> float:
    """Spread of the registered camera centres over the median point depth (0 = pure rotation)."""
    if registered.sum() < 2 or len(points) == 0:
        return 0.0
    centres, depth = _centres_and_depth(w2c[registered], points)
    spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).max())
    return spread / max(depth, 1e-9)


def _centres_and_depth(w2c: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, float]:
    """(centres [T, 3], depth): the cameras' centres and the median over cameras of the
    median depth of ``points`` in each (absolute)."""
    R, t = w2c[:, :3, :3], w2c[:, :3, 3]
    centres = -np.einsum("tji,tj->ti", R, t)
    depth = np.median([(points @ R[i].T + t[i])[:, 2] for i in range(len(R))], axis=1)
    return centres, float(np.median(np.abs(depth)))


MAX_CAMERA_SPEED = 4.0
"""Fastest a reconstruction's camera centre may move between two posed frames, in median scene
depths per second, before its positions are taken for a failed solution and only its
rotations kept. Measured with ``fastest_move``: the synthetic video benchmark's clip 0.18
(40 frames at 10 fps, a 10-second script in 4 seconds); on the synthetic scene's true
cameras 0.07 (the demo scene: 100 frames at 10 fps), 0.63 (30 at 24 fps, seed 3), 1.22 (20
at 30 fps, seed 1) and 2.43 (20 at 60 fps, seed 2: the script in a third of a second); the
backpack clip 0.43 and the loading clip 0.57 (both walking hand-held cameras), the tennis
clip 0.29 and 8.9 with two of COLMAP's solutions for its panning camera: in the second the
camera teleports 3.2 m (0.3 of the scene's depth) between frames 4 and 5, back and forth
again by frame 30, and stands still after frame 48; the floor then came from a plane of 68
stray points, a median 2.9 m above the court's, and the body fit went from 0.088 to 0.12
(docs/experiments/2026-12-03-d-a-camera-that-teleports.md). A person walking with the
camera 1 m from the scene moves it 1.5 depths per second."""


def fastest_move(w2c: np.ndarray, registered: np.ndarray, points: np.ndarray, fps: float) -> tuple[float, int, int]:
    """(speed, a, b): the camera centre's fastest move between consecutive registered frames
    a < b, in median scene depths per second (the depth as in ``parallax_ratio``; frames
    between a and b that are not registered count in the time). (0, -1, -1) with fewer than
    two registered frames or no points."""
    idx = np.flatnonzero(registered)
    if len(idx) < 2 or len(points) == 0:
        return 0.0, -1, -1
    centres, depth = _centres_and_depth(w2c[idx], points)
    speed = np.linalg.norm(np.diff(centres, axis=0), axis=1) / np.diff(idx) * fps / max(depth, 1e-9)
    i = int(np.argmax(speed))
    return float(speed[i]), int(idx[i]), int(idx[i + 1])


# -- rotation-only fallback -----------------------------------------------------------


def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """R minimising sum |R a_i - b_i|^2 for unit vectors [N, 3]."""
    U, _, Vt = np.linalg.svd(b.T @ a)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def rotation_only(images: np.ndarray, static_masks: np.ndarray, K: np.ndarray, progress=None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Camera rotations from background homographies, chained from frame 0.

    Returns (world_to_camera [T, 4, 4] with zero translation, ok [T] bool: the pair to
    the previous frame gave a rotation, stats).
    """
    import cv2

    T = len(images)
    sift = cv2.SIFT_create(nfeatures=3000)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    Kinv = np.linalg.inv(K)
    feats = []
    for t in range(T):
        grey = cv2.cvtColor(images[t], cv2.COLOR_RGB2GRAY)
        kp, desc = sift.detectAndCompute(grey, static_masks[t].astype(np.uint8) * 255)
        feats.append((np.array([k.pt for k in kp], np.float64).reshape(-1, 2), desc))
        if progress:
            progress("features", t + 1, T)
    w2c = np.tile(np.eye(4), (T, 1, 1))
    ok = np.zeros(T, bool)
    ok[0] = True
    inlier_counts = []
    for t in range(1, T):
        R_rel = np.eye(3)
        (pa, da), (pb, db) = feats[t - 1], feats[t]
        if da is not None and db is not None and len(pa) >= 8 and len(pb) >= 8:
            knn = matcher.knnMatch(da, db, k=2)
            good = [m for m, *rest in knn if rest and m.distance < 0.75 * rest[0].distance]
            if len(good) >= 12:
                a = pa[[m.queryIdx for m in good]]
                b = pb[[m.trainIdx for m in good]]
                H, inl = cv2.findHomography(a, b, cv2.RANSAC, 2.0)
                if H is not None and inl.sum() >= 12:
                    inl = inl.ravel().astype(bool)
                    ba = np.c_[a[inl], np.ones(inl.sum())] @ Kinv.T
                    bb = np.c_[b[inl], np.ones(inl.sum())] @ Kinv.T
                    ba /= np.linalg.norm(ba, axis=1, keepdims=True)
                    bb /= np.linalg.norm(bb, axis=1, keepdims=True)
                    R_rel = _kabsch(ba, bb)  # camera t-1 -> camera t
                    ok[t] = True
                    inlier_counts.append(int(inl.sum()))
        w2c[t, :3, :3] = R_rel @ w2c[t - 1, :3, :3]
        if progress:
            progress("rotations", t + 1, T)
    stats = {"pairs_ok": int(ok[1:].sum()), "median_inliers": float(np.median(inlier_counts)) if inlier_counts else 0.0}
    return w2c, ok, stats


def background_residuals(images: np.ndarray, static_masks: np.ndarray, K: np.ndarray, tracks: list[np.ndarray],
                         offsets: tuple[int, ...] = (1, 8, 32), side: int = 256) -> list[float]:
    """How well each of ``tracks`` (rotation-only cameras, world_to_camera [T, 4, 4]; their
    centres are ignored) explains the static background: the mean grey-level difference
    between each frame and the frames ``offsets`` before it warped onto it by the
    pure-rotation homography ``K R K^-1`` of the two cameras, over pixels that are
    ``static_masks`` [T, H, W] in both (inf where no pixel is), at most ``side`` pixels on
    the longer side; the frames are downscaled once for all tracks. The next frame catches a
    jump, the farther ones a drift (the homography chain, fitted pair by pair, drifts; COLMAP's rotations
    jump): on the basketball clip, COLMAP's rotations with a 0.75 degree jump leave 3.33 /
    9.73 / 22.11 grey levels at offsets 1 / 8 / 32, the chain 2.87 / 6.04 / 9.18. The
    offsets and ``side`` are set, not swept: the basketball clip is the one development clip
    without parallax, and the synthetic benchmark's videos have parallax, so they never
    reach this check (docs/experiments/2026-11-28-dev-clips-redrawn.md)."""
    import cv2

    T, H, W = images.shape[:3]
    s = min(1.0, side / max(H, W))
    w, h = max(1, int(round(W * s))), max(1, int(round(H * s)))
    Ks = np.diag([s, s, 1.0]) @ K
    Kinv = np.linalg.inv(Ks)
    small = [cv2.resize(images[t], (w, h), interpolation=cv2.INTER_AREA) for t in range(T)]  # uint8: 570 frames, 110 MB
    stat = [cv2.resize(static_masks[t].astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) for t in range(T)]

    def residual(w2c: np.ndarray) -> float:
        total, count = 0.0, 0
        for k in offsets:
            for t in range(k, T):
                R = w2c[t, :3, :3] @ w2c[t - k, :3, :3].T  # camera t-k -> camera t
                Hm = Ks @ R @ Kinv
                warped = cv2.warpPerspective(small[t - k], Hm, (w, h), flags=cv2.INTER_LINEAR).astype(np.float32)
                valid = (cv2.warpPerspective(stat[t - k], Hm, (w, h), flags=cv2.INTER_NEAREST) > 0) & (stat[t] > 0)
                n = int(valid.sum())
                if n:
                    total += float(np.abs(warped - small[t].astype(np.float32)).mean(-1)[valid].sum())
                    count += n
        return total / count if count else float("inf")

    return [residual(w2c) for w2c in tracks]


def proxy_points(
    images: np.ndarray,
    static_masks: np.ndarray,
    K: np.ndarray,
    w2c: np.ndarray,
    ground_normal: np.ndarray,
    ground_offset: float,
    backdrop_distance: float,
    n_points: int = 20000,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Scene points without triangulation: static pixels back-projected onto the ground
    plane (rays that hit it within reach) or onto a backdrop sphere of radius
    ``backdrop_distance`` around the camera. Used when the camera barely translates."""
    rng = np.random.default_rng(seed)
    T, H, W, _ = images.shape
    per = max(1, n_points // T)
    Kinv = np.linalg.inv(K)
    xyz, rgb = [], []
    for t in range(T):
        ys, xs = np.nonzero(static_masks[t])
        if len(xs) == 0:
            continue
        pick = rng.choice(len(xs), size=min(per, len(xs)), replace=False)
        u, v = xs[pick] + 0.5, ys[pick] + 0.5
        rays_c = np.c_[u, v, np.ones_like(u)] @ Kinv.T
        R, tt = w2c[t, :3, :3], w2c[t, :3, 3]
        centre = -R.T @ tt
        rays_w = rays_c @ R  # R^T applied to each row
        rays_w /= np.linalg.norm(rays_w, axis=1, keepdims=True)
        denom = rays_w @ ground_normal
        s_ground = -(centre @ ground_normal + ground_offset) / np.where(np.abs(denom) > 1e-9, denom, np.nan)
        use_ground = np.isfinite(s_ground) & (s_ground > 0) & (s_ground < backdrop_distance)
        s = np.where(use_ground, s_ground, backdrop_distance)
        xyz.append(centre + rays_w * s[:, None])
        rgb.append(images[t][ys[pick], xs[pick]])
    if not xyz:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    return np.concatenate(xyz), np.concatenate(rgb).astype(np.uint8)
