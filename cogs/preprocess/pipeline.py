"""`cogs preprocess`: the steps from a raw video to a native scene, each cached.

    frames -> persons -> objects -> cameras -> body -> masks -> object pose -> planes -> scene + preview

Every step stores its result under ``SCENE/.cache/<step>.npz`` with a ``<step>.json`` beside
it holding a key: a hash of the step's options and of the keys of the steps it reads. A
re-run loads every step whose key still matches and recomputes from the first that does
not (an interrupted run resumes where it stopped; changing any ``--object-box`` redoes the
object masks and what depends on them, not the frames or the person). ``--force`` ignores
the cache.

Nothing is written under ``--out`` itself until the end: the run works in the sibling
folder ``<out>.partial`` and renames it to ``--out`` only once ``cogs check`` accepts the
scene. An existing ``--out`` is replaced only with ``--overwrite`` (its cached steps are
reused), and only after the new scene is in place. A failed run leaves ``<out>.partial``
holding nothing but its cache, and says so: the same command resumes from it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from cogs.errors import UserError

log = logging.getLogger(__name__)

CACHE_VERSION = 1
PERSONS_VERSION = 7  # of the persons step (2: a body the detector cannot find is followed without the face; 4: landmarks re-detected where video tracking lost the body; 5: bodies laid on a hand dropped; 6: a followed person never takes somebody else's face; 7: frames the detector missed between or beside frames it found the person in are followed into by the landmark model)
TRACKER_VERSION = 32  # of the classical object tracker (5: a prompt in a hand starts carried by it; unclear masks get confidence 0.1; 6: an unclear GrabCut piece yields to the colour window; 7: masks along a forearm get confidence 0.1; 8: and the frames a motion cue followed them into; 9: the static scene judged after a long loss too; 10: an object lost while carried searched for where a hand has been; 11: GrabCut's spread onto a foot dropped; 12: doubtful runs tracked again from their other side; 13: a foot seen end-on sized from its shin; 14: a mask's parts that hold still with the room while the rest moves left out; 15: a clear view next to a hand does not end a carry; 16: nor does the other hand taking it over; 17: an object coloured like the person is looked for off the person, near the hands; 18: a prompt a pass sees carried starts carried in the pass the other way, and a motion fit in other colours is kept last where it moves; 19: the frames it was lost in judge the static scene too where the warp from those that found it fails; 20: discs over 128 px grown by a distance transform, where a dilation by OpenCV's digital ellipse took seconds; 21: a mask over 3x its prompt's area not trusted; 22: an object coloured like the person looked for off the body's landmark regions, not off the whole person's mask, nor off limbs dressed in other colours, from every prompt alike; 23: and found as what moves at either hand though never seen carried, its colour model kept from finds that do not look like it; 24: and at the hand as a thin frame and handle round strings that show the scene, and between two prompts the frames a pass lost beyond its reach taken from the other where it held on from the switch; 25: and kept on the body where a clear rigid fit carries it there from a view beside it, an arm swung across it; 26: a find that shows what the frames with the object elsewhere show there, off the person, is not trusted; 27: an object lost for longer than a carry is kept asks the colour search for its full evidence near a hand or the prediction too; 28: whether the object is coloured like the person is asked of the prompts either side of a pass's frames, not of every prompt; 29: between two prompts, their outlines followed by the image's edges where they meet in a hand; 30: a motion fit lying on an arm frame's mask is the arm, however much smaller; beyond the first and the last prompt, the outline of one a hand holds, while that hand holds it, where the colour cues doubt their finds; 31: any prompt's outline alone, beyond the first and the last prompt and between two whose outlines do not meet, in frames where the colour cues lost an object coloured like the person on the person, as far as it returns to the prompt followed back; a frame between two whose outline a hand holds held too; 32: a find a hand carries on from the frame before by a motion cue keeps that frame's confidence where its colours no longer resemble the prompt's): bumping it redoes the object masks (and what reads them)
SFM_VERSION = 6  # of the cameras step (2: COLMAP's two-view RANSAC seeded, its features extracted and bundles adjusted on one thread; 3: without parallax, COLMAP's rotations or the homography chain, whichever explains the background better; 4: features matched exactly by us, so the same frames give the same cameras; 5: a camera path faster than MAX_CAMERA_SPEED keeps only its rotations; 6: a mapper run that poses too few frames mapped again with the next seeds): bumping it redoes the cameras
MASKS_VERSION = 11  # of the body-based mask refinement (`bodymasks.py`; 5: no growth of a whole mask, no body where its fit is off; 6: nor a mask smaller than where the tracker saw the object clearly; 7: a mask's specks left out of its solidity; 8: the person's and the object's outlines moved onto the frame's edges; 9: the ring round a held object over 128 px grown by a distance transform; 10: the object's and the person's motions told apart by 2 px per 384 px of the frame's longer side, not 2 px; 11: the motion growth's other lengths so scaled, the held-in-front ring, the core and the ring the person's motion is sampled on): bumping it redoes the masks step
BODY_VERSION = 6  # of the body fit (`bodyfit.py`, `world.py`; 4: the scale from the person's motion where nothing else gives it; 5: the ground only where a foot is seen; 6: that scale taken from 5 % explained, not 20 %): bumping it redoes the body step
OBJECT_POSE_VERSION = 10  # of the initial object trajectory (`objectfit.py`; 10: a held object's depth from its size kept within reach of the holding hand; 9: the proxy chosen on every view (up to 120), weighted as the pose's silhouettes, not on six clear ones; 8: doubted masks away from the hands left out, trusted ones may rest; 7: an object lost for good while carried stays in the hand to the clip's end, one first seen carried was in it from the start): bumping it redoes the object_pose step
STEPS = ["frames", "persons", "objects", "cameras", "body", "masks", "object_pose", "planes", "scene"]


def hosnerf_split(n: int) -> dict[str, list[int]]:
    """The hosnerf-16 protocol's split.

    n >= 32: the test frames are the first 16 of every (n // 16)-th frame (0, s, ..., 15 s);
    shorter clips hold out every 4th frame starting at frame 2 (2, 6, 10, ...), which keeps
    both ends in training and leaves clips of one or two frames entirely for training.
    """
    if n >= 32:
        s = n // 16
        test = [i * s for i in range(16)]
    else:
        test = list(range(2, n, 4))
    test_set = set(test)
    return {"train": [i for i in range(n) if i not in test_set], "test": test}


# -- cache ----------------------------------------------------------------------------


class Cache:
    """Step results on disk. ``keys[step]`` is the *result id* of a loaded or computed step
    (a fresh id each time a step is computed), so whatever reads a recomputed step is
    recomputed too, even when the step's own options did not change."""

    def __init__(self, root: Path, force: bool = False):
        self.root = Path(root)
        self.force = force
        self.keys: dict[str, str] = {}

    def key(self, step: str, params: dict, deps: list[str]) -> str:
        blob = json.dumps({"v": CACHE_VERSION, "step": step, "params": params, "deps": [self.keys[d] for d in deps]}, sort_keys=True, default=str)
        return hashlib.sha1(blob.encode()).hexdigest()

    def load(self, step: str, key: str) -> tuple[dict, dict] | None:
        meta_path, data_path = self.root / f"{step}.json", self.root / f"{step}.npz"
        if self.force or not meta_path.exists() or not data_path.exists():
            return None
        try:
            meta = json.loads(meta_path.read_text())
            if meta.get("key") != key:
                return None
            with np.load(data_path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except (OSError, ValueError, json.JSONDecodeError, EOFError):
            return None  # a step interrupted while writing: recompute it
        return arrays, meta

    def save(self, step: str, key: str, arrays: dict, meta: dict, compress: bool) -> None:
        from cogs.data.io import atomic_writer

        self.root.mkdir(parents=True, exist_ok=True)
        tmp = self.root / f"{step}.tmp.npz"
        (np.savez_compressed if compress else np.savez)(tmp, **arrays)
        tmp.replace(self.root / f"{step}.npz")
        # The key is written last: a step counts as done only once its data is complete.
        # Both files are replaced, never rewritten in place: a cache may share them (hard
        # links) with the scene it replaces.
        with atomic_writer(self.root / f"{step}.json") as f:
            f.write(json.dumps({**meta, "key": key}, indent=1, default=_json_default))

    def n_steps(self) -> int:
        """How many step results the folder holds."""
        try:
            return sum(1 for p in self.root.glob("*.json"))
        except OSError:
            return 0

    def result_id(self, meta: dict) -> str:
        return str(meta.get("result_id", meta.get("key")))


def _json_default(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    return str(x)


# -- the run --------------------------------------------------------------------------


@dataclass
class RunReport:
    scene: Path
    preview: Path
    seconds: dict[str, float] = field(default_factory=dict)
    cached: list[str] = field(default_factory=list)
    stats: dict = field(default_factory=dict)


class _Progress:
    """One rich progress display; each step is a task with stage, count, rate and eta."""

    def __init__(self, enabled: bool):
        from cogs.log import progress

        self.enabled = enabled
        self.p = progress() if enabled else None

    def __enter__(self):
        if self.p:
            self.p.__enter__()
        return self

    def __exit__(self, *exc):
        if self.p:
            self.p.__exit__(*exc)

    def task(self, label: str, total: int) -> Callable[..., None]:
        from cogs.log import rate_text

        if not self.p:
            return lambda done, info="", total_now=None: None
        tid = self.p.add_task(label, total=max(total, 1), rate="", info="")
        started = time.perf_counter()

        def update(done: int, info: str = "", total_now: int | None = None) -> None:
            kw = {"total": max(total_now, 1)} if total_now else {}
            self.p.update(tid, completed=done, rate=rate_text(done, started), info=info, **kw)

        return update

    def done(self, label: str, note: str) -> None:
        if self.p:
            self.p.add_task(f"{label} [dim](cached)[/dim]", total=1, completed=1, rate="", info=note)


def run_preprocess(cfg) -> RunReport:
    """Run every step for a `cogs.preprocess.command.Preprocess` configuration."""
    return _Runner(cfg).run()


PARTIAL = ".partial"
"""Suffix of the sibling folder a run works in (`<out>.partial`)."""


class _Runner:
    def __init__(self, cfg):
        self.cfg = cfg
        self.final = Path(cfg.out)
        self.out = self.final.parent / f"{self.final.name}{PARTIAL}"  # every step writes here
        self.cache = Cache(self.out / ".cache", force=cfg.force)
        self.report = RunReport(scene=self.final, preview=self.final / "preview.png")
        self.n_steps = len(STEPS)

    # -- the work folder --------------------------------------------------------------

    def _prepare_work(self) -> None:
        """`<out>.partial` holding only a cache: the one a failed run left (resumed), or a
        new one seeded with the cache of the scene being replaced."""
        import shutil

        from cogs.data.outdir import MARKER, new_staging

        work = self.out
        if work.exists() or work.is_symlink():
            if not (work.is_dir() and (work / MARKER).exists()):
                raise UserError(f"{work} is in the way: cogs preprocess works in this folder and did not make what is "
                                "there; move or delete it")
            self._keep_only_cache()
            work.mkdir(exist_ok=True)
            (work / MARKER).touch()
            if self.cache.n_steps():
                log.info("resuming from the steps cached in %s", self.cache.root)
            return
        new_staging(work)
        old = self.final / ".cache"
        if old.is_dir() and not self.cfg.force:
            # Hard links where possible: a step's files are only ever replaced, never rewritten.
            self.cache.root.mkdir()
            for f in old.iterdir():
                if f.is_file() and f.suffix in (".json", ".npz"):
                    try:
                        os.link(f, self.cache.root / f.name)
                    except OSError:
                        shutil.copy2(f, self.cache.root / f.name)

    def _keep_only_cache(self) -> None:
        """Remove from the work folder everything but the cache (the folder goes when the
        cache holds no finished step)."""
        import shutil

        from cogs.data.outdir import MARKER

        work = self.out
        if not work.is_dir():
            return
        keep = {".cache", MARKER} if self.cache.n_steps() else set()
        for entry in work.iterdir():
            if entry.name in keep:
                continue
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
        if not keep:
            shutil.rmtree(work, ignore_errors=True)

    def _failed_note(self) -> str:
        if self.out.is_dir() and self.cache.n_steps():
            return (f"nothing was written to {self.final}; the {self.cache.n_steps()} step(s) finished so far are cached "
                    f"in {self.cache.root}: run the same command again to resume from them (or delete {self.out})")
        return f"nothing was written to {self.final}"

    def run(self) -> RunReport:
        from cogs.data.outdir import claimed

        self.cfg.check_options()
        with claimed(self.final):
            return self._run_claimed()

    def _run_claimed(self) -> RunReport:
        self._prepare_work()
        try:
            self._run()
            replaced = self._publish()
        except UserError as e:
            self._keep_only_cache()
            raise UserError(f"{e}\n{self._failed_note()}") from None
        except BaseException:
            self._keep_only_cache()
            log.error("%s", self._failed_note())
            raise
        if replaced:
            log.info("replaced %s in %s", replaced, self.final)
        return self.report

    def _publish(self) -> str | None:
        from cogs.data.outdir import put_in_place

        return put_in_place(self.out, self.final)

    # Each step: params that define it, steps it reads, compute -> (arrays, meta).
    def _step(self, ui: _Progress, i: int, name: str, params: dict, deps: list[str], compute, compress: bool = True):
        key = self.cache.key(name, params, deps)
        label = f"[{i}/{self.n_steps}] {name}"
        hit = self.cache.load(name, key)
        if hit is not None:
            self.cache.keys[name] = self.cache.result_id(hit[1])
            arrays, meta = hit
            ui.done(label, meta.get("summary", ""))
            self.report.cached.append(name)
            self.report.seconds[name] = 0.0
            self.report.stats[name] = meta.get("stats", {})
            return arrays, meta
        t0 = time.perf_counter()
        arrays, meta = compute(label)
        dt = time.perf_counter() - t0
        meta = {**meta, "seconds": dt, "result_id": uuid.uuid4().hex}
        self.cache.save(name, key, arrays, meta, compress)
        self.cache.keys[name] = meta["result_id"]
        self.report.seconds[name] = dt
        self.report.stats[name] = meta.get("stats", {})
        return arrays, meta

    def _run(self) -> None:
        from cogs.preprocess.frames import display_rotation

        cfg = self.cfg
        src = Path(cfg.input)
        stat = src.stat()
        frame_params = {"input": str(src.resolve()), "size": stat.st_size if src.is_file() else None,
                        "mtime": stat.st_mtime, "stride": cfg.stride, "limit": cfg.limit, "start": cfg.start,
                        "max_side": cfg.max_side}
        rotation = display_rotation(src)
        if rotation:  # frames are turned upright (earlier versions cached them as stored)
            frame_params["display_rotation"] = rotation
        with _Progress(cfg.progress) as ui:
            self._ui = ui
            fr, fmeta = self._step(ui, 1, "frames", frame_params, [], self._frames, compress=False)
            images = fr["images"]
            T, H, W, _ = images.shape
            self.source_size = tuple(fmeta["source_size"])
            self.fps = float(fmeta["fps"])
            self.source_indices = fr["source_indices"]
            self.positives, self.negatives = cfg.object_prompts()
            self.person = cfg.person_prompt()
            boxes = self.positives + self.negatives + ([self.person] if self.person else [])
            if boxes:  # the boxes against the frames, before the steps that take long
                from cogs.preprocess.prompts import check_against_frames

                check_against_frames(boxes, self.source_size, T)

            person_params = {"version": PERSONS_VERSION, "threshold": cfg.person_threshold, "refine": cfg.refine_person_masks,
                             "sam2": str(cfg.sam2_checkpoint)}
            if self.person:  # only then, so that caches made before the option stay valid
                person_params["person_box"] = self.person.record()
            pe, pmeta = self._step(ui, 2, "persons", person_params, ["frames"], lambda lb: self._persons(lb, ui, images))
            self.person_choice = pmeta.get("stats", {}).get("followed")  # chosen among several people, or None
            if not pe["detected"].any():
                hands = pmeta.get("stats", {}).get("bodies_on_hands", [])
                seen = (f"; the bodies they did find, in {len(hands)} frame(s) from frame {hands[0]} on, lay on a hand "
                        "(MediaPipe Hands found it there): cogs needs the person's body in view, from the shoulders to "
                        "the hips at least, not hands alone") if hands else ""
                raise UserError(f"no person detected in any of the {T} frames of {src}: MediaPipe's detector (it finds a "
                                "person by the face) and its landmark model around "
                                f"{'the --person-box' if self.person else 'the whole first frame'} found none{seen}. "
                                "Where a body is in view, give --person-box FRAME X0 Y0 X1 Y1 around it, or a larger "
                                f"--max-side (now {cfg.max_side})")

            has_object = bool(self.positives) or cfg.object_masks is not None
            ob_params = {**self._prompt_params(), "masks": str(cfg.object_masks), "sam2": str(cfg.sam2_checkpoint),
                         "tracker": TRACKER_VERSION,
                         **({"track_side": cfg.track_side} if cfg.track_side else {})}
            if has_object:
                ob, _ = self._step(ui, 3, "objects", ob_params, ["frames", "persons"], lambda lb: self._objects(lb, ui, images, pe))
                obj_masks = ob["masks"].astype(bool)
                from cogs.preprocess.persons import body_on_object_warning

                text = body_on_object_warning(pe["kp2d"], obj_masks)
                if text:
                    log.warning("%s", text)
            else:
                self.cache.keys["objects"] = "none"
                ui.done(f"[3/{self.n_steps}] objects", "no object prompt: scene without object")
                obj_masks, ob = None, None

            focal = cfg.focal_px if cfg.focal_px else cfg.focal_factor * max(W, H)
            K = np.array([[focal, 0.0, 0.5 * W], [0.0, focal, 0.5 * H], [0.0, 0.0, 1.0]])
            cam, cmeta = self._step(ui, 4, "cameras", {
                "focal": focal, "sfm": cfg.sfm, "min_registered": cfg.min_registered,
                "min_parallax": cfg.min_parallax, "dilate": cfg.mask_dilate_px, "matching": cfg.matching,
                "exhaustive_max_frames": cfg.exhaustive_max_frames, "version": SFM_VERSION,
            }, ["frames", "persons", "objects"], lambda lb: self._cameras(lb, ui, images, pe["masks"].astype(bool), obj_masks, K))

            from cogs.preprocess.bodyfit import ADULT_STATURE_M

            stature = cfg.person_height or ADULT_STATURE_M
            bo, bmeta = self._step(ui, 5, "body", {"version": BODY_VERSION, "model": cfg.body_model, "iterations": cfg.body_iterations,
                                                   "stature_m": stature},
                                   ["persons", "cameras"],
                                   lambda lb: self._body(lb, ui, images, pe, cam, cmeta, K, stature))

            # The fitted body's silhouette as a second source of evidence for both masks; they
            # come out disjoint (one owner per pixel: the object wins).
            ms, _ = self._step(ui, 6, "masks", {"version": MASKS_VERSION, "model": cfg.body_model}, ["frames", "persons", "objects", "body"],
                               lambda lb: self._masks(lb, ui, images, pe, obj_masks, ob, bo, K))
            human_masks = ms["human"].astype(bool)
            if obj_masks is not None:
                obj_masks = ms["object"].astype(bool)

            if has_object:
                # The trajectory fits the object's whole outline: the tracker's masks (not the
                # masks step's), fingers included (they hide the object, they do not shrink
                # it). Fitted to the masks without them it comes out smaller, so nearer:
                # centre error 16 -> 17.5 % of the depth on the 30-frame benchmark clip.
                op, _ = self._step(ui, 7, "object_pose", {"version": OBJECT_POSE_VERSION}, ["frames", "objects", "masks", "body"],
                                   lambda lb: self._object_pose(lb, ui, images, ob, human_masks, bo, K))
            else:
                self.cache.keys["object_pose"] = "none"
                ui.done(f"[7/{self.n_steps}] object_pose", "no object")
                op = None

            pl, _ = self._step(ui, 8, "planes", {"max_planes": cfg.max_planes}, ["body"], lambda lb: self._planes(lb, ui, bo))

            update = ui.task(f"[9/{self.n_steps}] scene", 2)
            t0 = time.perf_counter()
            self._write_scene(images, human_masks, obj_masks, bo, bmeta, op, pl, K, cmeta,
                              None if ob is None else ob["confidence"])
            update(1, "scene written")
            from cogs.preprocess.preview import contact_sheet

            contact_sheet(self.out, self.out / "preview.png", kp2d=pe["kp2d"], registered=bo["registered"].astype(bool), camera_method=cmeta["method"],
                          radii=None if op is None else op["radii"], proxy=None if op is None else str(op["kind"]),
                          n_frames=cfg.preview_frames, body_model=cfg.body_model)
            update(2, str(self.report.preview))
            self.report.seconds["scene"] = time.perf_counter() - t0

    def _prompt_params(self) -> dict:
        """The object prompts as the objects step's key holds them: one box on one frame as
        before several prompts existed (so such a scene's cache stays valid), otherwise
        every box as [frame, x0, y0, x1, y1]."""
        pos, neg = self.positives, self.negatives
        if len(pos) <= 1 and not neg:
            return {"box": list(pos[0].box) if pos else None, "frame": pos[0].frame if pos else 0}
        return {"boxes": [p.record() for p in pos], "negative_boxes": [n.record() for n in neg]}

    # -- steps ----------------------------------------------------------------------

    def _frames(self, label):
        from cogs.preprocess.frames import read_frames

        cfg = self.cfg
        total = cfg.limit or _estimate_frames(cfg.input, cfg.stride, cfg.start)
        ui_update = self._ui_task(label, total)
        fr = read_frames(cfg.input, stride=cfg.stride, limit=cfg.limit, max_side=cfg.max_side, start=cfg.start,
                         on_frame=lambda k: ui_update(k, "", max(k, total)))
        meta = {"fps": fr.fps, "source_size": list(fr.source_size), "summary": f"{fr.n} frames {fr.width}x{fr.height}",
                "stats": {"n_frames": fr.n, "width": fr.width, "height": fr.height}}
        return {"images": fr.images, "source_indices": fr.source_indices}, meta

    def _ui_task(self, label, total):
        return self._ui.task(label, total)

    def _persons(self, label, ui, images):
        from cogs.preprocess.objects import scale_box
        from cogs.preprocess.persons import choose_person, detect_persons, follow_person, refine_masks_sam2, without_bodies_on_hands

        T = len(images)
        update = ui.task(label, T)
        size = (images.shape[2], images.shape[1])
        choice = None
        if self.person is not None:
            box = scale_box(self.person.box, self.source_size, size)
            track = follow_person(images, self.person.frame, box, on_frame=lambda k: update(k),
                                  mask_threshold=self.cfg.person_threshold)
        else:
            near = None
            if self.positives:  # the person handling the object is the subject
                p0 = self.positives[0]
                near = (p0.frame, scale_box(p0.box, self.source_size, size))
            choice = choose_person(images, near)
            if choice is None:  # one person in view: MediaPipe's own video-mode tracking
                track = detect_persons(images, on_frame=lambda k: update(k), mask_threshold=self.cfg.person_threshold)
            else:
                k, box = choice
                followed = [k, *(round(float(v), 1) for v in scale_box(box, size, self.source_size))]
                log.warning("several people in view: following the one %s, in the box %s on frame %d "
                            "(pixels of the input video); name another with --person-box FRAME X0 Y0 X1 Y1",
                            "nearest the object's box" if near else "nearest the centre",
                            " ".join(f"{v:g}" for v in followed[1:]), k)
                track = follow_person(images, k, box, on_frame=lambda n: update(n), mask_threshold=self.cfg.person_threshold)
        on_hands: list[int] = []

        def off_hands(track, finder: str):
            bar = ui.task(f"{label} (hands)", int(track.detected.sum())) if track.detected.any() else None
            track, dropped, whole = without_bodies_on_hands(images, track, on_frame=bar)
            if dropped:
                log.warning("%s laid a body on a hand in %d frame(s): %s%s (MediaPipe Hands found the hand there); %s",
                            finder, len(dropped), dropped[:10], "..." if len(dropped) > 10 else "",
                            "it was following a hand, so none of its finds is kept" if whole else "the body there is interpolated")
            on_hands.extend(dropped)
            return track

        track = off_hands(track, "MediaPipe Pose")
        if not track.detected.any():
            track = off_hands(self._body_without_face(images, size, update), "MediaPipe's landmark model")
        elif not track.detected.all():
            from cogs.preprocess.persons import fill_missing

            update_f = ui.task(f"{label} (missed frames)", int((~track.detected).sum()))
            track, filled = fill_missing(images, track, on_frame=lambda k: update_f(k), mask_threshold=self.cfg.person_threshold)
            if filled:
                log.warning("MediaPipe's person detector missed the person in %d frame(s) it found them around: %s%s; "
                            "the landmark model followed the body into them from the frames next to them, without the "
                            "face's keypoints", len(filled), filled[:10], "..." if len(filled) > 10 else "")
        if self.cfg.refine_person_masks and self.cfg.sam2_checkpoint is None:
            import cv2

            from cogs.preprocess.persons import refine_mask_boundary

            update_r = ui.task(f"{label} (boundary)", T)
            for t in range(T):
                if track.detected[t] and track.masks[t].any():
                    ys = np.nonzero(track.masks[t])[0]
                    band = max(2, int(0.02 * (ys.max() - ys.min() + 1)))
                    # Only near the cleaned mask: refinement moves boundaries, never adds blobs.
                    near = cv2.dilate(track.masks[t].astype(np.uint8), np.ones((2 * band + 1,) * 2, np.uint8)) > 0
                    track.masks[t] = refine_mask_boundary(images[t], track.probs[t], self.cfg.person_threshold) & near
                update_r(t + 1)
        if self.cfg.sam2_checkpoint is not None:
            update2 = ui.task(f"{label} (sam2)", T)
            track.masks = refine_masks_sam2(images, track, self.cfg.sam2_checkpoint, self.cfg.sam2_config, on_frame=lambda k: update2(k))
        n = int(track.detected.sum())
        missing = [i for i in range(T) if not track.detected[i]]
        meta = {"summary": f"person in {n}/{T} frames", "stats": {"detected": n, "missing_frames": missing[:50],
                                                                  "bodies_on_hands": sorted(set(on_hands))[:50]}}
        if choice is not None:
            meta["stats"]["followed"] = followed
        if missing and n:
            log.warning("no person found in %d frame(s): %s%s; the body there is interpolated",
                        len(missing), missing[:10], "..." if len(missing) > 10 else "")
        return track.arrays(), meta

    def _body_without_face(self, images, size, update):
        """MediaPipe's detector found nobody (it finds people by the face): the body's
        landmarks tracked from the --person-box, or from the whole frame, by the landmark
        model alone (``persons.follow_body``)."""
        from cogs.preprocess.objects import scale_box
        from cogs.preprocess.persons import follow_body

        T, H, W = images.shape[:3]
        if self.person is not None:
            frame, box, where = self.person.frame, scale_box(self.person.box, self.source_size, size), f"the {self.person.option} box"
        else:
            frame, box, where = 0, np.array([0.0, 0.0, W, H]), "the whole of frame 0"
        track = follow_body(images, frame, box, on_frame=lambda k: update(k), mask_threshold=self.cfg.person_threshold)
        if track.detected.any():
            log.warning("MediaPipe's person detector found nobody (it finds people by the face: is the head out of view?); "
                        "the body was followed from %s by the landmark model alone, in %d of %d frames, without the "
                        "face's keypoints", where, int(track.detected.sum()), T)
        return track

    def _objects(self, label, ui, images, pe):
        from cogs.branches.object import ObjectConfig
        from cogs.preprocess import objects as O

        min_confidence = ObjectConfig().min_confidence  # frames under it do not supervise the object

        cfg = self.cfg
        T, H, W, _ = images.shape
        update = ui.task(label, T)
        cues: list[str] = []
        sources: list[int] = []
        if cfg.object_masks is not None:
            masks = O.read_mask_folder(cfg.object_masks, T, (W, H), self.source_indices)
            conf = masks.reshape(T, -1).any(1).astype(np.float64)
            update(T)
        else:
            from cogs.preprocess.prompts import (box_mask, edge_prompt_warning, edge_run, guessed_prompt_warning,
                                                 lookalike_prompt_warning, lost_stretch_warning, person_lookalike_warning,
                                                 small_prompt_warning, untrusted_stretches)

            scaled = [(p.frame, O.scale_box(p.box, self.source_size, (W, H))) for p in self.positives]
            scaled_neg = [(p.frame, O.scale_box(p.box, self.source_size, (W, H))) for p in self.negatives]
            negative = {}
            for k, box in scaled_neg:
                negative[k] = negative.get(k, np.zeros((H, W), bool)) | box_mask(box, (H, W))
            if cfg.sam2_checkpoint is not None:
                masks = O.propagate_masks_sam2(images, scaled, cfg.sam2_checkpoint, cfg.sam2_config, self.out / ".cache" / "sam2",
                                               negatives=scaled_neg, on_frame=lambda n: update(n))
                for k, region in negative.items():
                    masks[k] &= ~region
                conf = masks.reshape(T, -1).any(1).astype(np.float64)
            else:
                prompts = {}
                for p, (k, box) in zip(self.positives, scaled):
                    prompts[k], guessed = O.grabcut_box(images[k], box)
                    if guessed:
                        log.warning("%s", guessed_prompt_warning(p))
                    if k in negative:
                        prompts[k] &= ~negative[k]
                    if not prompts[k].any():
                        raise UserError(f"{p.option} {p.text}: GrabCut found no object in the box on frame {k}")
                    for text in (small_prompt_warning(p, int(prompts[k].sum()), (W, H), cfg.max_side),
                                 None if guessed else edge_prompt_warning(p, *edge_run(prompts[k], box))):
                        if text:
                            log.warning("%s", text)
                lookalike: dict[int, float] = {}
                like_person: dict[int, float] = {}
                still: dict[int, int] = {}
                masks, conf = O.track(images, prompts, cfg.track_side, human_probs=pe["probs"], kp2d=pe["kp2d"],
                                      negatives=negative, cues=cues, sources=sources, lookalike=lookalike, still=still,
                                      like_person=like_person, on_frame=lambda n: update(n))
                for p in self.positives:
                    for text in (lookalike_prompt_warning(p, lookalike[p.frame]), person_lookalike_warning(p, like_person[p.frame])):
                        if text:
                            log.warning("%s", text)
                text = lost_stretch_warning(untrusted_stretches(conf, min_confidence), T)
                if text:
                    log.warning("%s", text)
        if not masks.any():
            raise UserError("the object masks are empty in every frame (check --object-box / --object-masks)")
        n = int(masks.reshape(T, -1).any(1).sum())
        lost = [i for i in range(T) if not masks[i].any()]
        stats = {"frames_with_object": n, "empty_frames": lost}
        if cues:  # which cue of the classical tracker found each frame
            stats["cues"] = {c: cues.count(c) for c in sorted(set(cues)) if c}
        if still:  # pixels of the masks left out as still scene: each prompt's, then the frames' that lost some
            prompted = [p.frame for p in self.positives]
            stats["still_px"] = {"prompts": {str(k): still.get(k, 0) for k in prompted},
                                 "frames": sorted(k for k in still if k not in prompted)[:50],
                                 "frames_px": int(sum(v for k, v in still.items() if k not in prompted))}
        if len(self.positives) > 1:  # which prompt's pass each frame's mask came from
            stats["prompt_of_frame"] = sources
        trusted = int((conf >= min_confidence).sum())
        stats["trusted_frames"] = trusted
        return {"masks": masks, "confidence": conf}, {"summary": f"object in {n}/{T} frames, {trusted} trusted", "stats": stats}

    def _cameras(self, label, ui, images, person_masks, obj_masks, K):
        from cogs.preprocess import sfm as S

        cfg = self.cfg
        T = len(images)
        static = np.stack([S.feature_mask(person_masks[t], None if obj_masks is None else obj_masks[t], cfg.mask_dilate_px) for t in range(T)])
        update = ui.task(label, 3 * T)
        phases = {"features": 0, "matching": T, "mapping": T + 1, "rotations": T}

        def prog(phase, done, total):
            base = phases.get(phase, 0)
            span = 1 if phase == "matching" else T
            update(base + int(done * span / max(total, 1)), phase, 2 * T + 1)

        stats: dict = {}
        method = None
        if cfg.sfm in ("auto", "colmap") and T >= 3:
            matching = cfg.matching if cfg.matching != "auto" else ("exhaustive" if T <= cfg.exhaustive_max_frames else "sequential")
            poses, xyz, rgb, st = S.run_colmap(images, static, K, self.out / ".cache" / "colmap", matching=matching, progress=prog,
                                               enough=math.ceil(cfg.min_registered * T))
            st["matching"] = matching
            stats["colmap"] = st
            w2c, reg = S.fill_unregistered(poses, T)
            frac = reg.mean()
            parallax = S.parallax_ratio(w2c, reg, xyz)
            speed, a, b = S.fastest_move(w2c, reg, xyz, self.fps)
            stats["colmap"].update(registered_fraction=float(frac), parallax=parallax, fastest_move=speed)
            enough_points = len(xyz) >= max(100, 5 * int(reg.sum()))
            physical = speed <= S.MAX_CAMERA_SPEED
            if frac >= cfg.min_registered and parallax >= cfg.min_parallax and physical and enough_points:
                method = "colmap"
            elif frac >= cfg.min_registered and enough_points:
                # Rotations are good, but the points have no usable depth (a tripod-like clip)
                # or the camera's path is not one a camera can take: keep the rotations and fix
                # the centre.
                if not physical:
                    stats["colmap"]["jump"] = [a, b]
                    log.info("structure from motion moves the camera %.1f scene depths per second between frames %d and "
                             "%d (at most %.1f is taken for a real path): its camera positions are dropped and only its "
                             "rotations kept", speed, a, b, S.MAX_CAMERA_SPEED)
                w2c[:, :3, 3] = 0.0  # every camera at the world origin
                method, xyz, rgb = "colmap-rotation", np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
            if method == "colmap-rotation" and cfg.sfm == "auto":
                # Without parallax COLMAP's rotations can jump between two frames (0.75 degrees
                # on the basketball clip: its background smeared in training, 3.8 dB lower). The
                # homography chain is the other guess; the rotations under which the background
                # agrees better across frames are kept.
                phases.update(features=T + 1, rotations=2 * T)
                w2c_h, reg_h, st_h = S.rotation_only(images, static, K, progress=prog)
                res = dict(zip(("colmap-rotation", "rotation"), S.background_residuals(images, static, K, [w2c, w2c_h])))
                stats["rotation"], stats["background_residual"] = st_h, res
                if res["rotation"] < res["colmap-rotation"]:
                    w2c, reg, method = w2c_h, reg_h, "rotation"
                    stats["note"] = (f"the homography chain explains the background better than COLMAP's rotations: "
                                     f"{res['colmap-rotation']:.2f} -> {res['rotation']:.2f} grey levels")
            elif method is None and cfg.sfm == "colmap":
                raise UserError(f"structure from motion posed {reg.sum()}/{T} frames with {len(xyz)} points; try --sfm auto (rotation-only fallback)")
        if method is None:
            phases.update(features=0, rotations=T)
            w2c, reg, st = S.rotation_only(images, static, K, progress=prog)
            stats["rotation"] = st
            method, xyz, rgb = "rotation", np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
        update(3 * T, method, 3 * T)
        n_reg = int(reg.sum())
        summary = f"{method}: {n_reg}/{T} frames posed, {len(xyz)} points" + (f" ({stats['note']})" if "note" in stats else "")
        meta = {"method": method, "summary": summary, "stats": stats}
        return {"world_to_camera": w2c, "registered": reg, "points_xyz": xyz, "points_rgb": rgb, "static": static}, meta

    def _body(self, label, ui, images, pe, cam, cmeta, K, stature_m: float):
        from cogs.body import load_body_model
        from cogs.preprocess import bodyfit as B
        from cogs.preprocess import sfm as S
        from cogs.preprocess import world as Wd

        cfg = self.cfg
        T = len(images)
        iters = cfg.body_iterations
        update = ui.task(label, iters + max(20, iters // 4) + 2)
        model = load_body_model(cfg.body_model)
        kp2d, kp3d = pe["kp2d"].astype(np.float64), pe["kp3d"].astype(np.float64)
        shape = B.choose_shape(model, height_m=stature_m)
        scale = B.limb_scale(model, shape, kp3d)
        R_cam, t_cam = B.init_camera_space(kp2d, kp3d, K, scale)
        kp3d_f = B.fill_missing(kp3d)
        feet_cam = t_cam[:, None, :] + scale * kp3d_f[:, Wd.FOOT_LANDMARKS]
        up_cam = Wd.up_in_camera(kp3d)
        update(1, "aligning world")
        w2c_s, reg = cam["world_to_camera"], cam["registered"].astype(bool)
        xyz_s, rgb = cam["points_xyz"], cam["points_rgb"]
        method = cmeta["method"]
        notes = {}
        if method == "colmap":
            al = Wd.align_sfm(w2c_s, reg, xyz_s, K, kp2d, up_cam, feet_cam, t_cam)
            w2c = al.cameras(w2c_s)
            xyz = al.points(xyz_s)
        else:
            al, cam_h = Wd.align_static(w2c_s, kp2d, up_cam, feet_cam, t_cam)
            w2c = al.cameras(w2c_s)
            dist = float(np.nanmedian(np.linalg.norm(t_cam, axis=1)))
            xyz, rgb = S.proxy_points(images, cam["static"].astype(bool), K, w2c, np.array([0.0, 0.0, 1.0]), 0.0,
                                      backdrop_distance=max(3.0, 2.5 * dist))
            notes["camera_height_m"] = cam_h
        notes.update(al.notes)
        R_w, root_w = B.camera_to_world_init(R_cam, t_cam, w2c)
        t0 = time.perf_counter()
        fit = B.fit_body(model, kp2d, kp3d, K, w2c, shape, R_w, root_w, ground=(np.array([0.0, 0.0, 1.0]), 0.0),
                         iterations=iters, on_step=lambda i, loss: update(1 + i, f"loss {loss:.4g}"))
        update(iters + max(20, iters // 4) + 2, f"mean 2D error {np.nanmean(fit.reprojection_error):.3f} of height")
        hand = [model.bone_index(b) for b in ("wrist.L", "wrist.R", "finger3-1.L", "finger3-1.R")]
        stats = {
            "scale_m_per_unit": al.scale, "ground_from": al.ground_source, "shape": shape.tolist(),
            "stature_m": stature_m, "stature_from": "--person-height" if self.cfg.person_height else "adult prior",
            "reprojection_error_mean": float(np.nanmean(fit.reprojection_error)),
            "reprojection_error_max": float(np.nanmax(fit.reprojection_error)), "fit_seconds": time.perf_counter() - t0,
            **notes,
        }
        text = B.poor_fit_warning(stats["reprojection_error_mean"], notes.get("scale"))
        if text:
            log.warning("%s", text)
        return {
            "world_to_camera": w2c, "registered": reg, "points_xyz": xyz.astype(np.float32), "points_rgb": rgb.astype(np.uint8),
            "shape": fit.track.shape, "pose": fit.track.pose, "transl": fit.track.transl, "joints": fit.joints_world,
            "hand_joints": fit.joints_world[:, hand], "root": fit.joints_world[:, model.bone_index("root")],
            "reprojection_error": fit.reprojection_error,
        }, {"summary": f"{cfg.body_model} on {T} frames, 2D error {stats['reprojection_error_mean']:.3f} of height", "stats": stats}

    def _masks(self, label, ui, images, pe, obj_masks, ob, bo, K):
        from cogs.body import load_body_model
        from cogs.preprocess.bodymasks import body_parts, refine_masks

        T, H, W, _ = images.shape
        update = ui.task(label, 2 * T)
        model = load_body_model(self.cfg.body_model)
        parts = body_parts(model, bo["shape"], bo["pose"], bo["transl"], bo["world_to_camera"], K, W, H)
        update(T, "body drawn")
        # Masks from the user (--object-masks) or from SAM2 are taken as they are: the fitted
        # body only corrects MediaPipe's person mask and the classical tracker's fingers.
        cfg = self.cfg
        human, obj, stats = refine_masks(images, pe["masks"].astype(bool), obj_masks, parts, pe["detected"].astype(bool),
                                         on_frame=lambda k: update(T + k),
                                         fingers=cfg.object_masks is None and cfg.sam2_checkpoint is None,
                                         person_edges=cfg.sam2_checkpoint is None, fit_error=bo["reprojection_error"],
                                         confidence=None if ob is None else ob["confidence"])
        arrays = {"human": human}
        if obj is not None:
            arrays["object"] = obj
        summary = (f"forearm +{stats['forearm_px']} px in {stats['frames_with_forearm']} frames, fingers -{stats['finger_px']} px "
                   f"in {stats['frames_with_fingers']}, bleed -{stats['bleed_px']} px"
                   + (f"; the body fit is off its keypoints in {stats['frames_body_unfit']} frames, not used there"
                      if stats["frames_body_unfit"] else ""))
        return arrays, {"summary": summary, "stats": stats}

    def _object_pose(self, label, ui, images, ob, human_masks, bo, K):
        import torch

        from cogs.body import load_body_model
        from cogs.branches.object import ObjectConfig
        from cogs.preprocess.objectfit import fit_object

        masks = ob["masks"].astype(bool)
        T = len(masks)
        update = ui.task(label, T)
        # A carried object turns with the fitted forearm that holds it, from a frame where its
        # rotation is known (at rest, or clearly seen); the fitted body's root carries it
        # across the other frames the masks lose.
        model = load_body_model(self.cfg.body_model)
        with torch.no_grad():
            A, _ = model.bone_transforms(torch.tensor(bo["pose"], dtype=torch.float64), torch.tensor(bo["transl"], dtype=torch.float64),
                                         torch.tensor(bo["shape"], dtype=torch.float64))
        A = A[..., :3, :3].numpy()
        root = A[:, model.bone_index("root")]
        forearms = np.stack([A[:, model.bone_index(f"lowerarm01.{side}")] for side in "LR"], axis=1)
        fit = fit_object(masks, ob["confidence"], K, bo["world_to_camera"], bo["hand_joints"].astype(np.float64),
                         bo["root"].astype(np.float64), human_masks=human_masks, ground=(np.array([0.0, 0.0, 1.0]), 0.0),
                         images=images, carrier_world=root, forearm_world=forearms, trusted=ObjectConfig().min_confidence,
                         on_frame=lambda k: update(k))
        stats = {"proxy": fit.kind, "radii_m": fit.radii_m.tolist(), "mean_iou": float(np.nanmean(fit.iou)), "depth_source": fit.depth_source}
        return {"quats": fit.track.quats, "translations": fit.track.translations, "centre": fit.track.centre,
                "radii": fit.radii_m, "kind": np.array(fit.kind), "iou": fit.iou, "carried": fit.carried}, {
                    "summary": f"{fit.kind} proxy, silhouette IoU {stats['mean_iou']:.2f}", "stats": stats}

    def _planes(self, label, ui, bo):
        from cogs.geometry.planes import ransac_planes

        update = ui.task(label, 1)
        xyz = bo["points_xyz"].astype(np.float64)
        planes = [{"normal": [0.0, 0.0, 1.0], "offset": 0.0, "label": "ground", "inliers": -1}]
        if len(xyz) >= 50:
            found = ransac_planes(xyz, max_planes=self.cfg.max_planes, threshold_m=0.03, min_inliers=max(50, int(0.05 * len(xyz))), iterations=500, seed=0)
            for i, p in enumerate(found):
                n, d = p.normal, p.offset
                if abs(n[2]) > 0.95 and abs(d * np.sign(n[2])) < 0.1:
                    planes[0]["inliers"] = int(len(p.inliers))  # the ground, confirmed by the points
                    continue
                planes.append({"normal": n.tolist(), "offset": float(d), "label": f"plane{i}", "inliers": int(len(p.inliers))})
        update(1, f"{len(planes)} planes")
        arr = np.array([[*p["normal"], p["offset"]] for p in planes])
        return {"planes": arr, "inliers": np.array([p["inliers"] for p in planes])}, {
            "labels": [p["label"] for p in planes], "summary": f"{len(planes)} planes", "stats": {"n_planes": len(planes)}}

    def _write_scene(self, images, human_masks, obj_masks, bo, bmeta, op, pl, K, cmeta, confidence=None):
        from cogs.data.scene import BodyTrack, CameraTrack, ObjectTrack, PlaneSpec, Scene, default_frame_ids, save_scene
        from cogs.data.validate import check_scene
        from cogs.data.scene import SceneError

        T, H, W, _ = images.shape
        labels = json.loads((self.cache.root / "planes.json").read_text())["labels"]
        planes = [PlaneSpec(np.asarray(p[:3], np.float64) / np.linalg.norm(p[:3]), float(p[3]), lab) for p, lab in zip(pl["planes"], labels)]
        xyz, rgb = bo["points_xyz"], bo["points_rgb"]
        if len(xyz) == 0:
            raise UserError("no scene points could be made (no static pixels?)")
        obj = None
        if op is not None:
            # The objects step's per-frame confidence (the tracker's; for SAM2's and the user's
            # masks 1 where a mask exists, 0 where empty), recorded so training can leave
            # the frames where the object was lost out of the object's supervision.
            assert confidence is not None and len(confidence) == T and np.isfinite(confidence).all()
            obj = ObjectTrack(centre=op["centre"].astype(np.float64), quats=op["quats"].astype(np.float64),
                              translations=op["translations"].astype(np.float64),
                              confidence=np.clip(np.asarray(confidence, np.float64), 0.0, 1.0))
        source = {
            "tool": "cogs preprocess",
            "input": str(Path(self.cfg.input)),
            "source_frames": [int(i) for i in self.source_indices],
            "source_size": list(self.source_size),
            "camera_method": cmeta["method"],
            "registered_frames": [int(i) for i in np.flatnonzero(bo["registered"])],
            "split_protocol": "hosnerf-16" if T >= 32 else "every 4th from frame 2",
            "body_fit": bmeta.get("stats", {}),
        }
        if self.person is not None:  # in pixels of the input video, a frame among the kept ones
            source["person_prompt"] = self.person.record()
        elif self.person_choice:  # several people in view, none named: the one followed
            source["person_followed"] = self.person_choice
        if self.positives:  # in pixels of the input video, frames among the kept ones
            source["object_prompts"] = {"boxes": [p.record() for p in self.positives],
                                        "negative_boxes": [n.record() for n in self.negatives]}
        elif self.cfg.object_masks is not None:
            source["object_masks"] = str(Path(self.cfg.object_masks))
        if op is not None:
            source["object_init"] = {"shape": str(op["kind"]), "radii_m": [float(r) for r in op["radii"]]}
            if "carried" in op:  # (a step cached by an older version has no such record)
                source["object_init"]["carried_frames"] = np.flatnonzero(op["carried"]).tolist()
        scene = Scene(
            root=None,
            name=self.cfg.name or Path(self.cfg.input).stem,
            width=W, height=H, fps=self.fps,
            frame_ids=default_frame_ids(T),
            split=hosnerf_split(T),
            cameras=CameraTrack(K=np.tile(K, (T, 1, 1)), world_to_camera=bo["world_to_camera"].astype(np.float64)),
            body=BodyTrack(model=self.cfg.body_model, shape=bo["shape"], pose=bo["pose"], transl=bo["transl"]),
            object=obj,
            points_xyz=xyz.astype(np.float32),
            points_rgb=rgb.astype(np.uint8),
            planes=planes,
            source=source,
        )
        scene.set_pixels(images, human_masks, obj_masks)
        save_scene(scene, self.out)
        problems = check_scene(self.out)
        if problems:  # a bug in cogs, not the user's input: keep the traceback (the scene is never put in place)
            raise AssertionError(str(SceneError(self.out, problems)))


def _known_models() -> list[str]:
    from cogs.body import MODELS

    return sorted(MODELS)


def _estimate_frames(path, stride: int, start: int) -> int:
    p = Path(path)
    if p.is_dir():
        return max(1, (len([f for f in p.iterdir() if not f.name.startswith(".")]) - start + stride - 1) // stride)
    try:
        import av

        with av.open(str(p)) as c:
            n = c.streams.video[0].frames if c.streams.video else 0
        return max(1, (n - start + stride - 1) // stride) if n else 1
    except Exception:
        return 1
