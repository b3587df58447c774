"""The classical object tracker: one prompt mask -> a mask in every frame, no learned weights.

``propagate_masks`` walks away from the prompt frame in both directions. Each frame is
first compared with the static scene that the frames the pass came through show there
(``background.StaticScene``): static-scene pixels are never object (after a long loss,
the last frame it was found in still rules them out of the colour search), and pixels
that moved and are not the person are object whatever their colour. Then each frame
takes the first of four cues that holds (``_Tracker._step``):

1. **motion**: the object's last extent is placed where it was, where SIFT matches from
   remembered views carry it (``FeatureBank``), where dense optical flow carries it
   (``warp_mask_by_flow``), and, for an object carried by a hand, where the hand takes it
   (``move_with_hand``). Each placement is fitted rigidly (``align_mask``) to this frame's
   probability under a colour model of the object against its own surroundings in the
   last frame; the best fit wins if it fits well and still looks like the object. GrabCut
   then fits its outline to this frame (``segment.grabcut_from_seed``), without what it
   spreads onto a foot (``_Tracker._off_the_feet``), what the flow shows unchanged from
   the object stays object, and the hands' pixels (``hand_regions``) are taken out of
   the visible mask;
2. **colour**: the object-sized window with the best mean object probability over the
   whole frame (``locate``), weighted towards the motion prediction and the hands, then
   GrabCut seeded there (a fast or reappearing object: a bounced ball); where GrabCut
   keeps a piece the rest of the object surrounds (``unclear``: one panel of a ball
   between its seams), the window's probable pixels instead. An object lost while
   carried is looked for only where a hand has been since (``HAND_PATH_REACH``);
3. **hand**: for a few frames after an object seen carried by a hand was lost, the
   moving piece off the person at either hand (``moving_at_hand``): a handled object
   that turns shows faces no colour model has seen. An object coloured like the
   person's clothes is looked for there whether or not a carry was seen: held by its far
   end (a racket a handle's length from the palm) it never passes the carry test, and
   the colour search, which skips the body, misses it wherever a face-on view shows the
   scene through it or a swing blurs it into the scene. Without a static scene to compare
   with, GrabCut next to the carrying hand, off the person (``segment.grabcut_at_hand``);
   that find must differ from the previous frame with the background's motion undone
   (``_Tracker._unchanged``: a patch of background beside the hand does not), and it is
   tentative until the next frame sees it move with the hand;
4. **motion, whatever the colours**: the motion fit that cue 1 dropped for no longer looking
   like the object, where most of it moves and is not the person (``MOVING_FIT_SHARE``): a
   carried box turned to faces of other colours while the pose model's hand lies off it.

A prompt's mask first loses the parts that hold still with the room while the rest of it
moves (``without_still_parts``: the bed inside a box drawn around a guitar), and so does
every frame's mask at the end (a GrabCut outline spreading into that bed).

A prompt the fingers close over (``holding_hand``) starts carried by that hand, so the
search keeps to it and the hand cue may look there from the first frame on; so does a
prompt that the first pass from it saw carried by a hand from (nearly) its frame on, in the
pass the other way (``PROMPT_CARRY_SLACK``). A carry ends
where the object is seen clearly away from every visible hand (``HAND_NEAR``), not where a
loosely placed hand point merely fails the carry test, nor where the other hand takes it over.

Otherwise the object is hidden and the frame's mask is empty. Then every run of empty
frames that ends where the object was found again is tracked back into from there. A
convex object (a prompt mask of solidity >= 0.9: a ball, a box, a bottle) is kept to
the pieces of its mask that fit its outline (``drop_stray_pieces``). A frame's confidence
is the cue's, capped by how much the mask looks like the prompt (``resemblance``) except
where a hand carries it on from the frame before (it keeps that frame's confidence:
``CARRIED_TRUST_CUES``), and at 0.1 where its surroundings look like it too (``unclear``:
no evidence either way) or where it lies along a forearm (``on_forearm``: the arm holding
the object), or was followed there by motion from such a frame (``carried_on``), or shows
off the person what the frames that found the object elsewhere show there
(``_Tracker.shows_the_scene``: the floor a transparent bottle was lifted off, where the
track stayed).

Between two prompts, where a hand holds the object, the two prompts' outlines followed by
the image's edges alone (``outline.bridge``) give the frames the colour cues saw less than
clearly (a transparent bottle, whose colours are whatever lies behind it), at
``OUTLINE_CONFIDENCE``; frames they lost stay lost. Beyond the first prompt and the last,
and between two prompts whose outlines do not meet, each prompt's outline followed alone
(``outline.lone_pass``) gives, up to where the colour cues trust a find elsewhere
(``lone_outline_frames``), at ``LONE_CONFIDENCE``: the frames whose finds they doubt, while
the hand holding the prompt holds the outline; and the frames they lost an object coloured
like the person on the person (a white racket in front of a white shirt), while the
outline returns to the prompt when followed back.

Hands matter throughout: a handled object is always next to one, the fingers cover it, and
a hand looks like a skin-coloured object. Hands come from MediaPipe's pose keypoints
(wrist, pinky, index and thumb points of each hand). So do the feet for a kicked ball
(``foot_regions``: ankle, heel and toe): a motion fit lying mostly on them yields to any
place the colour search would take with the feet counted 5x less.
"""

from __future__ import annotations

import copy
import itertools
import logging
import warnings
from dataclasses import dataclass, field

import numpy as np

from cogs.errors import UserError
from cogs.preprocess.background import StaticScene, colour_residual, person_free
from cogs.preprocess.hands import HAND_LANDMARKS, filled_and_grown, forearm_regions, hand_points, hand_regions, holding_hand
from cogs.preprocess.outline import LONE_CONFIDENCE, OUTLINE_CONFIDENCE, bridge, lone_pass, within_reach
from cogs.preprocess.segment import (
    ColourModel,
    convex_hull,
    disk,
    fill_holes,
    grabcut_at,
    grabcut_at_hand,
    grabcut_from_seed,
    grabcut_with_seeds,
    grown,
    iou,
    largest_component_near,
    mask_stats,
    solidity,
    window,
)

log = logging.getLogger(__name__)

# The cues that place the last extent by a motion hint and fit it rigidly (``_by_motion``).
MOTION_CUES = ("stay", "flow", "features", "carried")
# A find by these cues from the frame before, while a hand carries the object (two frames
# or more), keeps the confidence of that frame where its resemblance to the prompt
# (``_Tracker.resemblance``) would cap it lower; never above the fit's own confidence. A
# carried box turns to faces the prompt never showed, in colours the scene has: on the
# synthetic video (the default scene), after the pick-up, frames 28-36 were fitted at
# 0.5-1.0 and covered the box (IoU 0.59-0.91 with the true masks), but resembled the
# prompt at 0.10-0.18, so the object's supervision left out its whole carry; the tennis
# racket's head at 27-30 (384 px) likewise. What drifts while carried is caught after the
# passes as before: onto the forearm (``carried_on``), the room (``shows_the_scene``).
# Chosen on the synthetic video at four settings and variants 10-17, and the development
# clips at 384 px and the default size (docs/experiments/2026-12-05-g-carried-trust.md).
CARRIED_TRUST_CUES = MOTION_CUES + ("moving",)
# ... and of each foot: ankle, heel, toe (foot index).
_FOOT_LANDMARKS = ((27, 29, 31), (28, 30, 32))
_KNEES = (25, 26)  # MediaPipe's left and right knees, for the feet above
# Frames back along a pass whose static scene a frame is compared with: near ones see the
# same view, far ones see what the person and the object covered in the near ones.
_SCENE_OFFSETS = (1, 2, 4, 8, 12)
# Where none of the frames that found the object lies within LOST_REFS frames (lost over the
# last ones) and the static-scene maps against those frames were thresholded at a residual
# noise above WARP_NOISE grey levels (their warp failed: the camera has moved on too far),
# the frames in between are references too, with only the person left out of them
# (``_Tracker._static_and_moving``). On variants 5, 7 and 11 of the synthetic video the box
# came back from behind the turning body; against frames 8-12 back alone the noise was 10-80
# (1-2 on frames the warp works for), everything was "static", and the box, carried on in
# view, was lost to the end: object IoU of the tracker's masks 0.555 / 0.547 / 0.536 ->
# 0.858 / 0.818 / 0.837. Without the noise condition (the lost frames always added) the box
# was lost after the turn on variants 6 and 9 instead (0.851 / 0.819 -> 0.559 / 0.537): it
# was in view, unfound, in those frames, and so called static. 10 is set, not swept: above
# the 1-2 of the synthetic video and the 0-5 median of the development clips, under the
# 12-20 where variants 5, 7 and 11 first fail. Checked on the seven development clips and
# the synthetic video at twenty settings (docs/experiments/2026-11-29-carried-from-the-prompt.md).
LOST_REFS = 2
WARP_NOISE = 10.0


# A found mask whose surroundings look like it at least this much (``_Tracker.unclear``)
# gets this confidence at most: below ``ObjectConfig.min_confidence`` (0.2), so it does not
# supervise the object, while the mask stays in the scene for the user to see. The share
# was measured on the six development clips and the synthetic video benchmark at three
# settings (docs/experiments/2026-11-28-held-in-hand-and-unclear-masks.md): on frames whose
# mask is the whole object it is at most 0.35 (0.11 on the synthetic clips); on the bottle
# clip's frames left on the floor it is 0.64-0.90.
UNCLEAR_SHARE = 0.5
UNCLEAR_CONFIDENCE = 0.1
# A frame the tracker found with less confidence than this is doubtful, and a run of them
# is tracked again from the clear frame at its far end (``cross_check``); where that pass
# disagrees (mask IoU below ``CROSS_AGREE``), its mask replaces the doubtful one if it is
# clear itself, and the frame's confidence falls to ``UNCLEAR_CONFIDENCE`` otherwise.
# 0.8 is the confidence the tracker already treats as a clear view (``_Tracker._update``);
# 0.5 is ``combine_passes``'s test of two passes on the same object. Neither was swept.
# Measured on the six development clips and the synthetic video benchmark at eight
# settings (docs/experiments/2026-11-28-tracks-from-both-sides.md): the juggled ball's
# frames on the shoe (47-48) and the basketball's partial balls (19-22) take the second
# pass's whole ball; a ball with a strip of its shadow (basketball 16) is left out of
# supervision; nothing else changes.
CLEAR_CONFIDENCE = 0.8
CROSS_AGREE = 0.5
# A mask more than this many times its prompt's area is not the object, whatever cue found it:
# a rigid object's outline does not triple as it turns, and the colour search already
# refuses such a find (its GrabCut leaked). A motion cue's track can grow that way, frame
# by frame, onto what lies next to it (a box's track spreading onto the wall behind it, a
# bottle's onto the forearms holding it): its confidence is capped at
# ``UNCLEAR_CONFIDENCE`` (``too_large``), so it does not supervise the object. Measured on
# the synthetic video benchmark at 21 settings and the seven development clips at 384 px
# (docs/experiments/2026-12-02-c-masks-larger-than-their-prompt.md): the synthetic frames
# over 3x (variant 10's 26 trusted frames on the wall, 3.1-9.5x; the 60-frame video's 41-54,
# already doubted) all have IoU < 0.06 with the truth, the correct ones (IoU >= 0.5) at most 1.9x;
# the largest correct ratio on the development clips is 2.51 (a backpack prompted edge-on,
# then turned to face the camera), then 2.0 (the juggled ball) and 1.97 (the tennis racket).
MAX_AREA_GROWTH = 3.0
# A mask with at least this share of its pixels on a forearm (``forearm_regions``, hands
# left out), in its frame and a neighbouring one, is the arm that holds the object rather
# than the object, which is held beyond the wrist: its confidence is capped at
# ``UNCLEAR_CONFIDENCE`` too (``on_forearm``). Measured on the six development clips and the
# synthetic video benchmark at three settings
# (docs/experiments/2026-11-28-masks-on-a-forearm.md): where the mask is the object it is
# at most 0.37 (a juggled ball passing in front of the arm; 0 on the synthetic clips); on
# the bottle clip's frames whose track followed a forearm it is 0.53-1.0 (0.31-0.49 where
# the mask lies across the hand as well: ``carried_on`` takes those where a motion cue
# followed the arm there).
ON_FOREARM_SHARE = 0.5
# A find at least this share of whose pixels (from at least ``SCENE_SEEN`` of them seen)
# show, within ``SCENE_TOL`` grey levels, what the nearest ``SCENE_REFS`` frames show there
# while the object is confidently elsewhere (``_Tracker.shows_the_scene``) is a patch of
# the room that looks like the object, not the object: its confidence is capped at
# ``UNCLEAR_CONFIDENCE``. The tracker's other static-scene tests compare a frame with those
# the pass came through, whose masks hide the very patch a track has settled on (the floor
# a transparent bottle was lifted off), so they cannot see it. At 960 px the bottle clip's
# colour finds on the floor at 29 and 30, trusted at 0.78 and 0.68, have 0.69 and 0.88 of
# their pixels within 8 grey levels; every find on the object that the rule can judge on
# the seven development clips at 384 px has at most 0.38 (the tennis racket over the
# banner; the basketball 0.35), and none reaches 0.5 on the clips at their default size or
# on the synthetic video at four settings. 0.5 lies between, not swept
# (docs/experiments/2026-12-04-d-a-track-on-the-floor.md).
SCENE_SHARE = 0.5
SCENE_SEEN = 0.5
SCENE_TOL = 8.0
SCENE_REFS = 4
# An object one of whose prompts' colour models calls at least this share of the person's
# pixels (off the object, on the prompt's frame) object has the colours of the person's
# clothes (a white racket held in front of a white shirt), and colours cannot tell the two
# apart: the object is then only looked for off the person's body (``body_regions``:
# MediaPipe's mask takes in a racket held out beside the legs, the landmarks' limbs do not
# reach there) and near the hands and its predicted place. A pass asks the prompts either
# side of its frames (``_Tracker.coloured_like_person``): between two prompts the rule holds
# if either shows the object so, beyond the first or last only if that one does. A prompt
# shows the object as it looks there: the tennis racket face-on on frame 70 shows the court
# through its strings (0.16, against 0.26 edge-on on frame 0), and the pass beyond it then
# follows the racket's head in front of the shins at 85-90; a box on a transparent bottle
# in front of a black shirt (0.27, against 0.14 and 0.16 on the bottle's other prompts)
# turns it on up to the neighbouring prompts, no further. The price: a prompt whose frame's
# person mask misses the clothes under-measures the share, and frees the frames beyond it
# (docs/experiments/2026-12-05-b-the-person-colour-rule-per-pass.md). A find lying mostly on the body
# (``ON_PERSON_SHARE`` of it) yields to what moves at a hand off the person, or the frame
# counts as lost, and a loss does not end a carry (in front of the person the object is as
# good as hidden; it has not left the hand). The share is 0.25 on a tennis clip whose track
# had left the racket for the shirt by frame 2 and stayed there to 92, 59 frames trusted;
# 0-0.17 on the six other development clips' prompts (second prompts included) and
# 0.04-0.06 on the synthetic video benchmark at twelve settings, where nothing changes
# (docs/experiments/2026-11-29-a-racket-coloured-like-the-shirt.md,
# docs/experiments/2026-12-03-a-racket-beyond-the-body.md).
LIKE_PERSON_SHARE = 0.2
ON_PERSON_SHARE = 0.5
# ... except on the limbs whose clothes do not look like it: a kind of limb
# (``limb_regions``) under this share of whose pixels (from at least ``MIN_LIMB_PIXELS``)
# a prompt's colour model calls object on that prompt's frame tells the object apart where
# it passes in front of it (a white racket before black shorts), on every frame, and is
# searched like the scene. On the tennis clip's first prompt the thighs (black shorts) are
# at 0.02, the shins 0.12, the upper arms 0.21, the forearms 0.35; on its second (frame 70,
# the racket and the hand over the thighs) the thighs are at 0.10. 0.1 is set, not swept:
# the one clip whose object has the person's colours has its shorts far under it and its
# shirt and skin above it.
TOLD_APART_SHARE = 0.1
MIN_LIMB_PIXELS = 30
# ... and except a rigid motion fit (stay, features, flow, carried) from the frame before,
# where the object lay off the body, that explains the object map at least this clearly (its
# confidence; ECC correlation 0.78): a racket whose head the forearm swings across, now in
# the person's mask and the arm's region. A patch of shirt looks the same all over and does
# not correlate with the head's outline that well. On the tennis clip the racket beside the
# hip at 101-102, the arm across it, is fitted at 0.91 and 0.75, while the fits that left it
# for the shirt in front of the body (2-22, the rule lifted) reach 0.57. 0.6 finds the same;
# 0.5 adds the racket before the shins (85-87, fitted at 0.50-0.60, right), but within the
# wrong fits' range. Only that clip's object has the person's colours among the development
# clips and the synthetic video, so it is chosen there alone; nothing else changes
# (docs/experiments/2026-12-03-f-an-arm-across-the-racket.md).
FIT_ON_PERSON = 0.7
# Where the body's regions (``body_regions``, every limb) cover less than this share of the
# person's mask, the landmarks do not say where the body is, and the whole mask is taken
# for it. Mean (90th percentile) share of the mask beyond the body over every frame of the
# development clips, the object's own masks left out: tennis 0.09 (0.12, at most 0.17, the
# racket where it was lost included), juggle 0.06 (0.08), bottle 0.12 (0.25), backpack 0.13
# (0.20), basketball 0.15 (0.26), but the seated guitar player 0.37 (0.52; legs crossed,
# their landmarks unseen) and the loader 0.51 (0.64): set between the two groups, not swept.
BODY_COVER = 0.65
# An object lost while carried is searched for by colour only within this many object sizes
# (the root of its usual area) of where a visible hand has been since it was last found: a
# carried object is still in the hand, or was put down by it. On a variant of the synthetic
# video the box, lost behind the turning body, was re-found on a green wallpaper the camera
# had just revealed (docs/experiments/2026-11-28-bodies-on-hands.md). Checked at 1.0 and
# 1.5 on the six development clips, the synthetic video benchmark at three settings, five
# variants of it and two unseen real clips: nothing else changes at either.
HAND_PATH_REACH = 1.5
# A clear view of a carried object ends the carry only where no visible hand lies within this
# share of the object's size (its bounding box's longer side) of its mask
# (``_Tracker._near_a_hand``); next to a hand that fails the carry test (touching, moving
# along), it stays carried. The pose model places the hands of a body turning away loosely:
# on a variant of the synthetic video the hand point sat 0.43 of the box's size off it, the
# carry ended, and the box, lost behind the body a frame later, was re-found by colour on
# the rug's edge coming into view and followed there for the clip's last 11 frames at
# confidence 0.54-0.71 (docs/experiments/2026-11-29-a-carry-kept-by-a-loose-hand.md).
# Tried at 0.5, 1.0 and 2.0 on the six development clips and the synthetic video at seven
# settings: each re-finds that box (and the 60-frame setting's, lost for 12 frames); 1.0 also
# moves the juggled ball at 71-79 by a few pixels, 2.0 at 10-35 and the bottle's mask on the
# floor at 11-21; 0.5 changes neither clip. (The demo scene runs no preprocessing.)
HAND_NEAR = 0.5
# A pass from a prompt that sees a hand carry the object from the prompt on, every frame
# found, tells the pass the other way from that prompt to start carried by that hand, if the
# hand lay within ``HAND_NEAR`` of the prompt's mask; the carry may begin this many frames
# after the prompt. A hand holding a box by its far side has its points 20-35 px (a third to
# a half of the box) off it, jumping by as much from one frame to the next, so the carry test
# fails on the prompt's own frame pair. On variant 1 of the synthetic video (prompt on the
# carried box, frame 29) the pass forwards saw the carry from frame 30 on; the pass back,
# not carried, lost the box behind the turning body and never found the other faces it
# showed before (frames 0-26 empty); started carried, the hand finds it at 23 and it is
# followed back to the table: the tracker's object IoU 0.165 -> 0.652. Set, not swept: 1
# lets the prompt's own frame pair fail. Checked on the seven development clips and the
# synthetic video at twenty settings: the loading clip's masks at 0-11 move by a few pixels,
# nothing else changes (docs/experiments/2026-11-29-carried-from-the-prompt.md).
PROMPT_CARRY_SLACK = 1
# A motion fit (cue 1) that no longer looks like the object by colour is kept, at confidence
# 0.5 at most, where neither the colour search nor the hand finds the object, if at least
# this share of it moves and is not the person (the static scene maps' "moving"). A box
# carried on after a turn shows faces of other colours: on variants 12 and 17 of the
# synthetic video the flow followed it at 29 but the colour check dropped the fit, the pose
# model's hands lay 50 px off (the carry had ended), and the box was lost to the end (object
# IoU of the tracker's masks 0.593 -> 0.855 and 0.585 -> 0.848). Kept at once instead of
# last, such fits took the sliver of one face the hand cue had found whole on the reference
# video (0.783 -> 0.678). Tried at 0.3, 0.5 and 0.7 on the seven development clips and the
# synthetic video at twenty settings: 0.5 and 0.7 give the same masks everywhere, 0.3 also
# moves variant 10's confidences on the painting its track is on either way; only variants
# 12 and 17 change (docs/experiments/2026-11-29-carried-from-the-prompt.md).
MOVING_FIT_SHARE = 0.5
# GrabCut refining a motion fit keeps nothing on a foot (``foot_regions``) farther than this
# share of the fitted shape's size from it (``_Tracker._off_the_feet``): a juggled ball took
# the white shoe it touched in on six frames of the juggle clip. Set, not swept (a tenth
# keeps GrabCut's usual few pixels of outline correction); checked on the six development
# clips, the synthetic video benchmark at three settings, five variants of it and an
# unseen real clip: only the juggle clip changes
# (docs/experiments/2026-11-28-a-ball-on-a-shoe.md).
FOOT_MARGIN = 0.1
# A foot seen end-on (pointing at or away from the camera) spans at least this share of
# the knee-to-ankle length in ``foot_regions`` (an adult's foot is about 0.6 of it): heel
# and toe 6.5 px apart under a 36 px shin left a juggled ball with the shoe it sat on.
# Tried at 0.35 and 0.45 on the six development clips and the synthetic video at eight
# settings (only the juggle clip changes), 0.55 and 0.65 on the juggle clip; 0.45 took the
# shoe off the most frames for the fewest made worse
# (docs/experiments/2026-11-28-feet-seen-end-on.md).
FOOT_SHIN_SHARE = 0.45

# -- motion cues ----------------------------------------------------------------------


def warp_mask_by_flow(prev_rgb: np.ndarray, rgb: np.ndarray, prev_mask: np.ndarray, margin: float = 1.5,
                      max_residual: float = 12.0) -> tuple[np.ndarray, np.ndarray]:
    """The previous frame's mask carried into this frame by dense optical flow, computed in a
    window around the mask -> (carried [H, W] bool, empty when nothing lands; the part of it
    whose colours match where the flow says they came from, within ``max_residual`` grey
    levels (``background.colour_residual``, 1 px tolerance), [H, W] bool).

    DIS flow (OpenCV's dense inverse search): its coarse-to-fine patch search follows a
    fast object much further than Farneback's polynomial expansion (on the synthetic
    benchmark, a gently moving box: IoU 0.98 against 0.42 while the camera pans). The
    matching part is the object still seen as it was: where something passed in front
    of it, the flow either follows the occluder (off the mask) or finds no match.
    """
    import cv2

    H, W = prev_mask.shape
    out, matched = np.zeros((H, W), bool), np.zeros((H, W), bool)
    if not prev_mask.any():
        return out, matched
    x0, y0, x1, y1 = window(prev_mask, margin)
    a = cv2.cvtColor(np.ascontiguousarray(rgb[y0:y1, x0:x1]), cv2.COLOR_RGB2GRAY)
    b = cv2.cvtColor(np.ascontiguousarray(prev_rgb[y0:y1, x0:x1]), cv2.COLOR_RGB2GRAY)
    # Flow from this frame to the previous one: where each pixel here came from.
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(a, b, None)
    gy, gx = np.mgrid[0 : y1 - y0, 0 : x1 - x0].astype(np.float32)
    mx, my = gx + flow[..., 0], gy + flow[..., 1]
    pm = prev_mask[y0:y1, x0:x1].astype(np.float32)
    out[y0:y1, x0:x1] = cv2.remap(pm, mx, my, cv2.INTER_LINEAR, borderValue=0.0) > 0.5
    source = cv2.remap(np.ascontiguousarray(prev_rgb[y0:y1, x0:x1]), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    matched[y0:y1, x0:x1] = out[y0:y1, x0:x1] & (colour_residual(rgb[y0:y1, x0:x1], source, 1) <= max_residual)
    return out, matched


def align_mask(mask: np.ndarray, prob: np.ndarray, margin: float = 1.0) -> tuple[np.ndarray | None, float]:
    """Move a mask rigidly (rotation and translation) onto where a probability map puts
    the object -> (moved mask [H, W] bool, or None when the fit fails; correlation).

    ECC (``cv2.findTransformECC``) maximises the correlation between the blurred mask and
    the blurred map in a window around the mask, starting where the mask is: a template
    fit that keeps the object's shape and lets its whole outline vote, so a few
    look-alike pixels nearby or a few missing ones (a new face, a finger) move it
    little. The correlation (at most 1) says how well the shape explains the map.
    """
    import cv2

    H, W = mask.shape
    _, s = mask_stats(mask)
    x0, y0, x1, y1 = window(mask, margin)
    sigma = max(2.0, 0.06 * float(s.max()))
    tmpl = cv2.GaussianBlur(mask[y0:y1, x0:x1].astype(np.float32), (0, 0), sigma)
    img = cv2.GaussianBlur(prob[y0:y1, x0:x1].astype(np.float32), (0, 0), 0.7 * sigma)
    warp = np.eye(2, 3, dtype=np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    try:
        cc, warp = cv2.findTransformECC(tmpl, img, warp, cv2.MOTION_EUCLIDEAN, criteria, None, 5)
    except cv2.error:
        return None, 0.0  # no convergence
    if not np.isfinite(cc):
        return None, 0.0  # a flat map (ECC divides by its spread): nothing object-like there
    A = warp.astype(np.float64)
    A[:, 2] += np.array([x0, y0]) - A[:, :2] @ np.array([x0, y0])  # window -> frame pixels
    moved = cv2.warpAffine(mask.astype(np.uint8), A, (W, H), flags=cv2.INTER_NEAREST) > 0
    return moved, float(cc)


@dataclass
class _View:
    """The object's SIFT keypoints in one frame where its mask is known."""

    t: int
    xy: np.ndarray  # [N, 2] pixels
    desc: np.ndarray  # [N, 128] float32
    mask: np.ndarray  # [H, W] bool


class FeatureBank:
    """Re-detection by local features: SIFT keypoints of the object in remembered views
    (the prompts', pinned, and the last ``recent`` frames found), matched into a new
    frame and verified by a RANSAC similarity transform.

    Unlike flow it follows a large jump (a fast lift) and finds the object again after an
    occlusion, as long as a face seen before is in view; unlike a colour model it
    ignores look-alike colours elsewhere, since the matches must agree on one rigid
    motion. Keypoints of whole frames are computed once and kept.
    """

    def __init__(self, images: np.ndarray, recent: int = 4, min_inliers: int = 5):
        import cv2

        self.images = images
        # A low contrast threshold: small, smooth or blurred objects still get keypoints.
        self.sift = cv2.SIFT_create(contrastThreshold=0.02)
        self.matcher = cv2.BFMatcher(cv2.NORM_L2)
        self.frames: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.pinned: list[_View] = []  # the prompts' views, never forgotten
        self.recent: list[_View] = []
        self.n_recent = recent
        self.min_inliers = min_inliers

    def _frame(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        if t not in self.frames:
            import cv2

            kps, desc = self.sift.detectAndCompute(cv2.cvtColor(self.images[t], cv2.COLOR_RGB2GRAY), None)
            xy = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
            self.frames[t] = (xy, np.zeros((0, 128), np.float32) if desc is None else desc)
        return self.frames[t]

    def _pairs(self, d_from: np.ndarray, d_to: np.ndarray) -> list:
        if len(d_from) < 2 or len(d_to) < 2:
            return []
        return [m[0] for m in self.matcher.knnMatch(d_from, d_to, k=2) if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]

    def view(self, t: int, mask: np.ndarray) -> _View:
        xy, desc = self._frame(t)
        H, W = mask.shape
        inside = mask[np.clip(xy[:, 1].astype(int), 0, H - 1), np.clip(xy[:, 0].astype(int), 0, W - 1)]
        return _View(t, xy[inside], desc[inside], mask)

    def pin(self, t: int, mask: np.ndarray) -> None:
        self.pinned.append(self.view(t, mask))

    def add(self, t: int, mask: np.ndarray) -> None:
        self.recent = [v for v in self.recent if v.t != t][-(self.n_recent - 1) :] + [self.view(t, mask)]

    def forget(self, keep) -> None:
        """Drop the recent views whose frame ``keep(t)`` rejects."""
        self.recent = [v for v in self.recent if keep(v.t)]

    def match(self, t: int) -> tuple[np.ndarray, int] | None:
        """(a remembered view's mask carried into frame t, inlier count) for the view with
        the most inliers, or None when no view matches."""
        import cv2

        xy, desc = self._frame(t)
        best = None
        views = self.recent[::-1]
        views += [p for p in self.pinned if all(v.t != p.t for v in views)]
        for v in views:
            pairs = self._pairs(v.desc, desc)
            if len(pairs) < self.min_inliers:
                continue
            src = v.xy[[m.queryIdx for m in pairs]]
            dst = xy[[m.trainIdx for m in pairs]]
            _, s = mask_stats(v.mask)
            A, inl = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=max(3.0, 0.05 * float(s.max())))
            if A is None:
                continue
            n = int(inl.sum())
            scale = float(np.sqrt(abs(np.linalg.det(A[:, :2]))))
            # A view further back in time may differ more in size than the last one.
            lo, hi = (0.5, 2.0) if abs(v.t - t) > 2 else (0.67, 1.5)
            if n < self.min_inliers or not lo <= scale <= hi:
                continue
            # The inliers must span the object, not sit on one spot (a repeated texture).
            if float(np.ptp(src[inl.ravel().astype(bool)], axis=0).max()) < 0.25 * float(s.max()):
                continue
            if best is None or n > best[2]:
                best = (v, A, n)
        if best is None:
            return None
        v, A, n = best
        H, W = v.mask.shape
        warped = cv2.warpAffine(v.mask.astype(np.uint8), A, (W, H), flags=cv2.INTER_NEAREST) > 0
        if warped.sum() < 0.5 * v.mask.sum():
            return None  # mostly outside the frame
        return warped, n

    def static_matches(self, t0: int, t1: int, static0: np.ndarray, most: int = 500) -> tuple[np.ndarray, np.ndarray]:
        """Keypoints of frame t0 where ``static0`` [H, W] bool (no person, no object; or
        any pixels whose keypoints are wanted) and their matches in frame t1 -> (xy0 [N,
        2], xy1 [N, 2]) pixels. At most ``most``
        keypoints, evenly picked, are matched: a textured scene has thousands, and a
        camera's motion needs far fewer (brute-force matching costs their product)."""
        xy0, d0 = self._frame(t0)
        xy1, d1 = self._frame(t1)
        H, W = static0.shape
        keep = np.flatnonzero(static0[np.clip(xy0[:, 1].astype(int), 0, H - 1), np.clip(xy0[:, 0].astype(int), 0, W - 1)])
        if len(keep) > most:
            keep = keep[np.linspace(0, len(keep) - 1, most).astype(int)]
        pairs = self._pairs(d0[keep], d1)
        return xy0[keep][[m.queryIdx for m in pairs]].reshape(-1, 2), xy1[[m.trainIdx for m in pairs]].reshape(-1, 2)

    def background_motion(self, t0: int, t1: int, static0: np.ndarray) -> np.ndarray | None:
        """[3, 3] homography taking frame t0's pixels where ``static0`` (no person, no
        object) to frame t1's, from matched keypoints; None when too few match."""
        import cv2

        src, dst = self.static_matches(t0, t1, static0)
        if len(src) < 8:
            return None
        Hm, inl = cv2.findHomography(src, dst, cv2.RANSAC, 3.0)
        return Hm if Hm is not None and inl.sum() >= 8 else None


# -- hands ----------------------------------------------------------------------------


def on_forearm(masks: np.ndarray, kp2d: np.ndarray, share: float = ON_FOREARM_SHARE) -> np.ndarray:
    """Frames whose mask lies on a forearm -> [T] bool: ``share`` or more of its pixels
    inside ``forearm_regions`` (the hands left out), in that frame and in the frame before
    or after it. A handled object is held beyond the wrist; a mask along the forearm, frame
    after frame, is a track that slid from the object onto the arm holding it (a
    transparent bottle in a fist, whose colours are the arm's and the clothes'). An object
    passing in front of the arm covers it for a frame or two, and not mostly: a juggled
    ball, at most 0.37 of its mask."""
    T, H, W = masks.shape
    on = np.zeros(T, bool)
    for t in range(T):
        n = int(masks[t].sum())
        if n:
            arm = forearm_regions(kp2d[t], (H, W)) & ~hand_regions(kp2d[t], (H, W))
            on[t] = (masks[t] & arm).sum() >= share * n
    return on & (np.r_[False, on[:-1]] | np.r_[on[1:], False])


def carried_on(arm: np.ndarray, masks: np.ndarray, cues: list[str], agree: float = 0.5) -> np.ndarray:
    """``arm`` [T] bool (``on_forearm``) grown along the track: a frame whose mask a motion
    cue placed (``MOTION_CUES``) and that lies on a neighbouring frame's mask on the arm (at
    least ``agree`` of its pixels) is on the arm too, whatever share of it lies on the
    forearm now: the track that slid onto the other arm went on to its wrist and hand, and
    shrank there to the hand (at 960 px the bottle clip's mask on forearm and hand at 90
    became the hand alone at 91, IoU 0.46 but 0.67 of it on 90's, and was trusted at
    91-94; IoU at least ``agree`` implies this). A colour find, the hand cue or a prompt is
    fresh evidence and stops it -> [T] bool. A track runs one way from the arm, so one
    sweep each way finds it."""
    out = arm.copy()
    T = len(out)
    for order, step in ((range(1, T), -1), (range(T - 2, -1, -1), 1)):
        for t in order:
            n = int(masks[t].sum())
            if (not out[t] and out[t + step] and cues[t] in MOTION_CUES and n
                    and int((masks[t] & masks[t + step]).sum()) >= agree * n):
                out[t] = True
    return out


def lone_outline_frames(k: int, shapes: dict[int, np.ndarray], masks: np.ndarray, conf: np.ndarray, held, returning=(),
                        unseen=lambda t: False) -> list[int]:
    """The frames a lone outline pass from prompt k (``outline.lone_pass``: {frame: [H, W]
    bool}) gives, in the order it reached them: ``held``, the frames whose outline the hand
    that holds the prompt holds, and ``returning``, those whose outline returns to the
    prompt followed back, each a run from the prompt on.

    The pass holds until the colour cues trust a find (``ObjectConfig.min_confidence``: it
    supervises the object branch) beyond the outline's reach (``outline.within_reach``): it
    has left the object, or the object has moved off where it went. Of the frames before
    that:
    - those whose find the colour cues doubt themselves (``UNCLEAR_CONFIDENCE``: its
      surroundings look like it, it lies on the arm, shows the room, or spread) take it
      where its hand holds it. Any other find is kept, seen in the frame's own colours (a
      carried box turned to a striped face is better found moving at the hand than by an
      outline whose fit the stripes pull aside).
    - those the colour cues lost where they do not look for the object (``unseen(t)``: one
      coloured like the person, its outline on the person) take it where it returns. A
      frame they lost elsewhere ends the pass: hidden, the object may come back turned or
      be put down, while an outline that stalled where it was still returns."""
    from cogs.branches.object import ObjectConfig

    trusted = ObjectConfig().min_confidence
    held, returning = set(held), set(returning)
    took = []
    for t in sorted(shapes, key=lambda t: abs(t - k)):
        if conf[t] >= trusted and not within_reach(masks[t], shapes[t]):
            break
        if conf[t] <= 0.0:
            if t not in returning or not unseen(t):
                break
            took.append(t)
        elif conf[t] <= UNCLEAR_CONFIDENCE and t in held:
            took.append(t)
    return took


def foot_regions(kp: np.ndarray, shape: tuple[int, int], min_visibility: float = 0.5) -> np.ndarray:
    """Pixels the visible feet (shoes) may cover -> [H, W] bool, from one frame's MediaPipe
    keypoints [33, 3]: the triangle of each foot's ankle, heel and toe points grown by
    0.4 x the foot's length, which takes in the shoe's width and sole. Chosen on the
    juggle and basketball clips with the synthetic video benchmark at two settings
    unchanged (0.25 left the juggle track on the shoes;
    docs/experiments/2026-11-27-tracker-feet-and-pieces.md).

    The length is heel to toe, but at least ``FOOT_SHIN_SHARE`` of the knee-to-ankle
    length where the knee is visible: a foot pointing at or away from the camera shows
    heel and toe a few pixels apart while its shoe still covers its full width and sole.
    """
    H, W = shape
    out = np.zeros((H, W), bool)
    for idx, knee_idx in zip(_FOOT_LANDMARKS, _KNEES):
        k = kp[list(idx)]
        if not np.isfinite(k).all() or k[:, 2].min() < min_visibility:
            continue
        length = float(np.linalg.norm(k[2, :2] - k[1, :2]))
        knee = kp[knee_idx]
        if np.isfinite(knee).all() and knee[2] >= min_visibility:
            length = max(length, FOOT_SHIN_SHARE * float(np.linalg.norm(knee[:2] - k[0, :2])))
        if length < 1.0:
            continue
        out |= filled_and_grown(k[:, :2], 0.4 * length, (H, W))
    return out


# The body's limbs by MediaPipe pose landmarks (``limb_regions``), each kind both sides'
# segments between joints; the torso is the quad of shoulders and hips.
_LIMBS = {"upper arm": ((11, 13), (12, 14)), "forearm": ((13, 15), (14, 16)),
          "thigh": ((23, 25), (24, 26)), "shin": ((25, 27), (26, 28))}
_TORSO = (11, 12, 24, 23)
# A limb's half-width as a share of its length (a thigh in shorts is about half as wide as
# it is long), and the torso's margin as a share of the shoulders' width.
LIMB_RADIUS = 0.25
TORSO_MARGIN = 0.1


def limb_regions(kp: np.ndarray, shape: tuple[int, int], min_visibility: float = 0.5) -> dict[str, np.ndarray]:
    """Pixels each kind of limb may cover -> {kind: [H, W] bool} (``_LIMBS``: upper arms,
    forearms, thighs, shins), from one frame's MediaPipe keypoints [33, 3]: the segment
    between each visible limb's joints grown by ``LIMB_RADIUS`` x its length."""
    import cv2

    H, W = shape
    out = {}
    for kind, pairs in _LIMBS.items():
        one = np.zeros((H, W), np.uint8)
        for a, b in pairs:
            k = kp[[a, b]]
            if not np.isfinite(k).all() or k[:, 2].min() < min_visibility:
                continue
            r = max(1, int(round(LIMB_RADIUS * float(np.linalg.norm(k[1, :2] - k[0, :2])))))
            cv2.line(one, *(tuple(int(v) for v in np.round(p)) for p in k[:, :2]), 1, 2 * r + 1)
        out[kind] = one > 0
    return out


def body_regions(kp: np.ndarray, shape: tuple[int, int], min_visibility: float = 0.5,
                 leave_out: tuple[str, ...] = ()) -> np.ndarray | None:
    """Pixels the body itself may cover -> [H, W] bool, from one frame's MediaPipe
    keypoints [33, 3]: the torso (the quad of shoulders and hips grown by ``TORSO_MARGIN``
    x the shoulders' width), the visible limbs (``limb_regions``) but the kinds in
    ``leave_out``, the head (``head_disc``), the hands and the feet. None where the torso
    is not seen.

    A person's segmentation mask takes in what the person holds out (a racket beside the
    legs); the body's joints do not reach there."""
    H, W = shape
    torso = kp[list(_TORSO)]
    if not np.isfinite(torso).all() or torso[:, 2].min() < min_visibility:
        return None
    body = filled_and_grown(torso[:, :2], TORSO_MARGIN * float(np.linalg.norm(torso[1, :2] - torso[0, :2])), (H, W))
    for kind, region in limb_regions(kp, shape, min_visibility).items():
        if kind not in leave_out:
            body |= region
    head = head_disc(kp)
    if head is not None:
        (cx, cy), r = head
        yy, xx = np.mgrid[:H, :W]
        body |= (xx + 0.5 - cx) ** 2 + (yy + 0.5 - cy) ** 2 <= r * r
    return body | hand_regions(kp, shape, min_visibility) | foot_regions(kp, shape, min_visibility)


def _visible(hands: np.ndarray | None, t: int, h: int | None) -> bool:
    return hands is not None and h is not None and bool(np.isfinite(hands[t, h]).all()) and hands[t, h, 2] >= 0.5


def _distance_to(mask: np.ndarray, point: np.ndarray) -> float:
    """Pixels from ``point`` (x, y) to the nearest mask pixel (0 inside)."""
    import cv2

    x0, y0, x1, y1 = window(mask, 0.5)
    xi, yi = int(round(point[0])) - x0, int(round(point[1])) - y0
    if not (0 <= xi < x1 - x0 and 0 <= yi < y1 - y0):
        return np.inf
    return float(cv2.distanceTransform((~mask[y0:y1, x0:x1]).astype(np.uint8), cv2.DIST_L2, 3)[yi, xi])


def carrying_hand(hands: np.ndarray | None, t0: int, t1: int, m0: np.ndarray, m1: np.ndarray,
                  touch: float = 0.3, moved_max: float = 1 / 3) -> int | None:
    """The hand (0 left, 1 right) that carries the object from frame t0 (mask ``m0``) to
    frame t1 (``m1``), or None.

    A hand carries the object when it touches the mask in both frames (within ``touch``
    x the object's size) and the object moved with it (the two displacements differ by
    less than ``moved_max`` x its size). A bounced ball touches the hand but moves on
    its own.
    """
    if hands is None:
        return None
    c0, _ = mask_stats(m0)
    c1, s1 = mask_stats(m1)
    size = float(max(s1.max(), 1.0))
    best, best_d = None, np.inf
    for h in range(2):
        if not (_visible(hands, t0, h) and _visible(hands, t1, h)):
            continue
        d = max(_distance_to(m0, hands[t0, h, :2]), _distance_to(m1, hands[t1, h, :2]))
        moved = np.linalg.norm((c1 - c0) - (hands[t1, h, :2] - hands[t0, h, :2]))
        if d <= touch * size and moved <= moved_max * size and d < best_d:
            best, best_d = h, d
    return best


def moving_at_hand(moving: np.ndarray, hand: np.ndarray, size: float, convex: bool = False,
                   person: np.ndarray | None = None) -> np.ndarray:
    """The moving thing a hand at pixel ``hand`` (x, y) holds -> [H, W] bool, empty when
    none: of ``moving`` [H, W] bool (pixels that are neither static scene nor the person),
    after an opening that drops the slivers left along the person's outline, the largest
    piece within 1.5 ``size`` (the object's side, pixels) of the hand (MediaPipe's hand
    points are the palm's, and an object may be held by its corner).

    Given the ``person`` [H, W] bool, the slivers are dropped as what lies next to the
    person and as pieces that are thin throughout, instead of by the opening: a racket's
    head face-on moves as a 1-2 px frame round strings that show the scene behind, and its
    handle is as thin, so the opening takes both; its head with the holes filled is thick.

    The piece may be less solid than a GrabCut find (solidity 0.7): where the object's
    colour happens to match the scene behind it, the static scene bites into it. For a
    ``convex`` object the piece's convex hull gives those bites back.
    """
    import cv2

    H, W = moving.shape
    r = max(1, int(0.05 * size))
    if person is None:
        opened = cv2.morphologyEx(moving.astype(np.uint8), cv2.MORPH_OPEN, disk(r))
    else:
        opened = (moving & ~cv2.dilate(person.astype(np.uint8), disk(r)).astype(bool)).astype(np.uint8)
    n, comp, stats, _ = cv2.connectedComponentsWithStats(opened, connectivity=8)
    if n <= 1:
        return np.zeros((H, W), bool)
    yy, xx = np.mgrid[:H, :W]
    near = (xx + 0.5 - hand[0]) ** 2 + (yy + 0.5 - hand[1]) ** 2 <= (1.5 * size) ** 2
    touching = np.unique(comp[near & (comp > 0)])
    if len(touching) == 0:
        return np.zeros((H, W), bool)
    best = touching[np.argmax(stats[touching, cv2.CC_STAT_AREA])]
    piece = fill_holes(comp == best)
    if solidity(piece) < 0.7:
        return np.zeros((H, W), bool)
    if person is not None and cv2.morphologyEx(piece.astype(np.uint8), cv2.MORPH_OPEN, disk(r)).sum() < 0.5 * piece.sum():
        return np.zeros((H, W), bool)  # thin throughout: a sliver
    return convex_hull(piece) if convex else piece


# A keypoint of a mask holds still with the room when it matched in at least two of the
# frames around it (``_SCENE_OFFSETS`` either way), one of them at least STILL_SPAN frames
# away, and every match lies within STILL_PX of where the camera's motion alone takes it
# (a bed: 0.1-0.6 px; a backpack hanging from a still hand drifts 1-7 px in 4 frames); it
# moves when it lies at least MOVING_PX off in two frames and in the median. Below
# MIN_STILL still or MIN_MOVING moving keypoints the mask is left as it is (an object at
# rest holds still as a whole; a stray match is no evidence). Chosen on the six
# development clips and the synthetic video benchmark
# (docs/experiments/2026-11-29-still-parts-of-a-mask.md).
STILL_PX = 1.0
STILL_SPAN = 4
MOVING_PX = 3.0
MIN_STILL = 5
MIN_MOVING = 5


def without_still_parts(rgb: np.ndarray, mask: np.ndarray, scene: StaticScene, k: int) -> np.ndarray:
    """Frame k's object ``mask`` [H, W] bool without the parts that hold still with the
    room while the rest moves -> [H, W] bool (a subset).

    GrabCut in a box takes whatever inside it stands out from around it: drawn around a
    guitar, a box holds part of the bed behind it, and later outlines spread into it.
    Keypoints on the mask are followed into the frames around frame k and compared with
    the camera's motion
    (``StaticScene.point_motion``); with enough of both kinds, GrabCut is run again on the
    mask with the still keypoints' neighbourhoods as background and the moving ones' as
    object, and the pieces that keep a moving keypoint stay. Uniform surfaces have no
    keypoints: they go with whichever seeds' colours they share."""
    import cv2

    T = len(scene.images)
    refs = [k + s * d for d in _SCENE_OFFSETS for s in (1, -1) if 0 <= k + s * d < T]
    xy, dist = scene.point_motion(k, mask, refs)
    if not len(xy):
        return mask
    seen = np.isfinite(dist)
    n = seen.sum(1)
    span = np.where(seen, np.abs(np.array(refs) - k)[None, :], 0).max(1)
    still = (n >= 2) & (span >= STILL_SPAN) & (np.where(seen, dist, 0.0).max(1) <= STILL_PX)
    far = np.where(seen, dist, 0.0) >= MOVING_PX
    med = np.array([np.median(d[f]) if f.any() else 0.0 for d, f in zip(dist, seen)])
    moving = (far.sum(1) >= 2) & (med >= MOVING_PX)
    if still.sum() < MIN_STILL or moving.sum() < MIN_MOVING:
        return mask
    H, W = mask.shape
    r = max(1, round(0.005 * max(H, W)))

    def seeds(points: np.ndarray) -> np.ndarray:
        out = np.zeros((H, W), np.uint8)
        for x, y in np.round(points).astype(int):
            cv2.circle(out, (int(x), int(y)), r, 1, -1)
        return out > 0

    keep, drop = seeds(xy[moving]), seeds(xy[still])
    out = grabcut_with_seeds(rgb, mask, keep & ~drop, drop & ~keep)
    _, lab = cv2.connectedComponents(out.astype(np.uint8))
    ids = np.unique(lab[keep & out])
    out = np.isin(lab, ids[ids > 0])
    if not out.any():
        return mask
    log.debug("frame %d: %d of the object mask's %d pixels hold still with the room (%d keypoints; %d move): left out",
              k, int(mask.sum() - out.sum()), int(mask.sum()), int(still.sum()), int(moving.sum()))
    return out


def drop_stray_pieces(mask: np.ndarray, area: float, grow: float = 1.5) -> np.ndarray:
    """A convex object's mask without the pieces that cannot belong to it -> [H, W] bool.

    The largest piece stays. Another piece stays only while the convex hull of it and the
    pieces kept so far covers at most ``grow`` x the larger of ``area`` (the object's
    usual extent, pixels) and the largest piece's hull: the parts of an object cut in two
    by a finger or an arm in front of it lie within its outline, a shoe or a trouser leg
    the motion fit carried along from a frame where they touched it does not (the juggled
    ball; docs/experiments/2026-11-27-tracker-feet-and-pieces.md). Pieces are tried
    largest first. ``grow`` 1.5 is set, not swept: it keeps a ball's two halves either side
    of an arm and drops the juggle clip's leg pieces; the synthetic video benchmark's mask
    IoUs (two settings) and the basketball clip's masks are unchanged by it.
    """
    import cv2

    n, comp, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 2:
        return mask
    order = 1 + np.argsort(-stats[1:, cv2.CC_STAT_AREA])
    kept = comp == order[0]
    limit = grow * max(float(area), float(convex_hull(kept).sum()))
    for k in order[1:]:
        both = kept | (comp == k)
        if convex_hull(both).sum() <= limit:
            kept = both
    return kept


def move_with_hand(mask: np.ndarray, kp0: np.ndarray, kp1: np.ndarray, hand: int) -> np.ndarray:
    """A mask carried by a hand from one frame (keypoints ``kp0`` [33, 3]) to the next
    (``kp1``): turned with the forearm (elbow to hand) and moved with the hand -> [H, W] bool."""
    import cv2

    elbow, wrist, pinky, index, _ = HAND_LANDMARKS[hand]
    a, b = kp0[[elbow, wrist, pinky, index], :2].astype(np.float64), kp1[[elbow, wrist, pinky, index], :2].astype(np.float64)
    pa, pb = a[1:].mean(0), b[1:].mean(0)
    va, vb = pa - a[0], pb - b[0]
    ang = np.arctan2(vb[1], vb[0]) - np.arctan2(va[1], va[0])
    sc = float(np.clip(np.linalg.norm(vb) / max(np.linalg.norm(va), 1e-6), 0.8, 1.25))
    R = sc * np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    A = np.concatenate([R, (pb - R @ pa)[:, None]], 1)
    H, W = mask.shape
    return cv2.warpAffine(mask.astype(np.uint8), A, (W, H), flags=cv2.INTER_NEAREST) > 0


# -- colour search --------------------------------------------------------------------


@dataclass
class _State:
    """What one pass knows about the object while walking through the frames."""

    centre: np.ndarray  # [2] pixels
    velocity: np.ndarray  # [2] pixels per frame
    size: np.ndarray  # [2] bbox width, height (clear views only)
    mask: np.ndarray  # [H, W] its extent in the last frame it was found (hidden parts included)
    visible: np.ndarray  # [H, W] its visible part there
    t: int  # that frame
    colour: float  # mean object probability of the visible part (global colour model)
    area: float  # usual extent in pixels (confident views only)
    lost: int = 0  # frames since it was found
    carrier: int | None = None  # the hand carrying it (0 left, 1 right)
    carried: int = 0  # consecutive frames it was seen carried by that hand
    held: bool = False  # carried (two frames or more) in the last frame it was found
    off_person: bool = False  # found there off the person's body, or kept on it by a clear fit from there
    into_gap: bool = False  # a pass back into frames the first pass lost it in
    pending: tuple | None = field(default=None, repr=False)  # see _Tracker.run


def locate(prob: np.ndarray, state: _State, hands: np.ndarray | None = None, floor: float = 0.35) -> tuple[np.ndarray, float, float]:
    """Centre, mean probability and prior plausibility of the object-sized window that best
    explains the frame.

    The whole frame is searched: a window's mean object probability is weighted by
    floor + (1 - floor) g, with g a Gaussian around the constant-velocity prediction (or
    around a visible hand [2, 3], whichever is larger: handled objects stay near hands),
    so a clearly better-looking window anywhere wins over a mediocre one nearby (a fast or
    briefly hidden object is re-acquired), while near-ties go to the motion prediction.
    ``floor`` 0 searches near the prediction and the hands only, and the prediction's
    reach then stays as it was when the object was lost.
    """
    import cv2

    H, W = prob.shape
    w, h = np.maximum(state.size, 3).astype(int)
    score = cv2.boxFilter(prob.astype(np.float32), -1, (int(w), int(h)), normalize=True, borderType=cv2.BORDER_CONSTANT)
    pred = state.centre + state.velocity
    diag = float(np.hypot(w, h))
    sigma = max(1.5 * diag, 2.0 * float(np.linalg.norm(state.velocity)))
    if floor > 0:
        sigma *= 1.0 + 0.5 * state.lost  # the longer lost, the further it may be
    yy, xx = np.mgrid[:H, :W]
    g = np.exp(-0.5 * ((xx + 0.5 - pred[0]) ** 2 + (yy + 0.5 - pred[1]) ** 2) / sigma**2)
    if hands is not None:
        for hx, hy, hv in hands:
            if np.isfinite(hx) and hv >= 0.5:
                dh2 = (xx + 0.5 - hx) ** 2 + (yy + 0.5 - hy) ** 2
                g = np.maximum(g, np.exp(-0.5 * dh2 / (0.75 * diag) ** 2))
    total = score * (floor + (1.0 - floor) * g)
    y, x = divmod(int(np.argmax(total)), W)
    return np.array([x + 0.5, y + 0.5]), float(score[y, x]), float(g[y, x])


def head_disc(kp: np.ndarray) -> tuple[np.ndarray, float] | None:
    """(centre [2], radius in pixels) of the person's head from one frame's MediaPipe
    keypoints [33, 3] (the face's eleven points, 1.3x their spread and 2 px); None where
    the face is not seen."""
    face = kp[:11]  # nose, eyes, ears, mouth
    if not np.isfinite(face).all() or np.median(face[:, 2]) < 0.5:
        return None
    c = face[:, :2].mean(0)
    return c, 1.3 * float(np.linalg.norm(face[:, :2] - c, axis=1).max()) + 2.0


def suppress_head(prob: np.ndarray, kp: np.ndarray, last_centre: np.ndarray) -> None:
    """Damp the object probability on the person's head, in place.

    Skin is the commonest look-alike of a handled object's colours and the face is always
    in view; unless the object was last seen on the head, head pixels count 5x less.
    """
    head = head_disc(kp)
    if head is None:
        return
    c, r = head
    if np.linalg.norm(last_centre - c) < r:
        return
    H, W = prob.shape
    x0, x1 = int(max(0, c[0] - r)), int(min(W, c[0] + r + 1))
    y0, y1 = int(max(0, c[1] - r)), int(min(H, c[1] + r + 1))
    if x1 <= x0 or y1 <= y0:
        return
    yy, xx = np.mgrid[y0:y1, x0:x1]
    inside = (xx + 0.5 - c[0]) ** 2 + (yy + 0.5 - c[1]) ** 2 <= r * r
    prob[y0:y1, x0:x1][inside] *= 0.2


# -- the tracker ----------------------------------------------------------------------


@dataclass
class _Found:
    """One frame's result: the visible mask, the extent (hand-covered parts included),
    confidence in [0, 1], the cue that found it and its colour score."""

    visible: np.ndarray
    extent: np.ndarray
    confidence: float = 0.0
    cue: str = ""
    colour: float = 0.0
    kept_on_person: bool = False  # on the body, kept as a clear fit from a view off it (``FIT_ON_PERSON``)


class _Tracker:
    """The state shared by every pass over the video: the frames, person and hand inputs,
    the prompt's colour model and the feature bank."""

    def __init__(self, images, prompt_mask, prompt_frame, human_probs, kp2d, min_score, adapt, min_align, max_hand_frames,
                 prompts: dict[int, np.ndarray] | None = None, negatives: dict[int, np.ndarray] | None = None):
        """``prompt_mask`` on frame ``prompt_frame``, or ``prompts`` {frame: [H, W] bool}
        (then those two are None); ``negatives`` {frame: [H, W] bool}: pixels that are
        not the object on that frame."""
        import cv2

        if prompts is None:
            prompts = {prompt_frame: prompt_mask}
        self.bank = FeatureBank(images)
        self.scene = None if human_probs is None else StaticScene(images, human_probs, self.bank.static_matches)
        self.still_px: dict[int, int] = {}  # per prompt frame: pixels left out as still scene
        if self.scene is not None:
            prompts = dict(prompts)
            for k in prompts:
                trimmed = without_still_parts(images[k], prompts[k], self.scene, k)
                self.still_px[k] = int(prompts[k].sum() - trimmed.sum())
                if self.still_px[k]:
                    log.info("the prompt on frame %d: %d of its mask's %d pixels hold still with the room while the rest "
                             "moves (scenery inside the box): left out", k, self.still_px[k], int(prompts[k].sum()))
                prompts[k] = trimmed
        self.prompts = prompts  # the prompts' masks, as tracked
        self.images = images
        self.human_probs = human_probs
        self.kp2d = kp2d
        self.hands = hand_points(kp2d)
        self.min_score = min_score
        self.adapt = adapt
        self.min_align = min_align
        self.max_hand_frames = max_hand_frames
        self.carried_from: dict[int, int] = {}  # prompt frame -> the hand a pass saw carry it from there on
        self.negatives = dict(negatives or {})
        rings = {k: cv2.dilate(m.astype(np.uint8), np.ones((5, 5), np.uint8), iterations=max(2, int(0.15 * mask_stats(m)[1].max() / 2))) > 0
                 for k, m in prompts.items()}
        self.distractors = None
        if human_probs is not None:
            # The person's colours in every frame (a held object inside the person's mask
            # contaminates this a little; the object's own histogram is far more peaked).
            keep = human_probs > 127
            for k, ring in rings.items():
                keep[k] &= ~ring
            flat = np.flatnonzero(keep)
            if len(flat):
                pick = np.random.default_rng(0).choice(flat, size=min(len(flat), 400_000), replace=False)
                self.distractors = images.reshape(-1, 3)[pick]
        if self.negatives:
            # What the user marked as not the object weighs as much as the person's colours
            # in every colour model, on every frame: a track that drifted onto the shorts
            # must not find the shorts object-like a frame later.
            neg = np.concatenate([images[k][m] for k, m in self.negatives.items()])
            if len(neg):
                n = len(neg) if self.distractors is None else len(self.distractors)
                neg = neg[np.arange(n) % len(neg)]
                self.distractors = neg if self.distractors is None else np.concatenate([self.distractors, neg])
        self.appearance = {}
        for k, m in prompts.items():
            self.bank.pin(k, m)
            base = ColourModel.fit(images[k], m, ~rings[k], self.distractors)
            _, s0 = mask_stats(m)
            # a box, a ball, a bottle are convex; not a mug by its handle
            self.appearance[k] = (base, float(base.prob(images[k])[m].mean()), float(m.sum()), solidity(m) >= 0.9, s0)
        self.like_person = {k: self.person_lookalike(k, m) for k, m in prompts.items()}
        # Whether some prompt shows the object in the person's colours; each pass then asks
        # the prompts either side of the frames it covers (``coloured_like_person``). The
        # limbs told apart are the object's against the clothes, from every prompt.
        self.colours_of_person = max(self.like_person.values(), default=0.0) >= LIKE_PERSON_SHARE
        self.limbs_apart = (tuple(sorted({kind for k, m in prompts.items() for kind in self.limbs_told_apart(k, m)}))
                            if self.colours_of_person else ())
        self._hidden: tuple[int, np.ndarray] | None = None  # the last frame's ``_hidden_on_person``
        self.use(next(iter(prompts)))
        self.masks: np.ndarray | None = None  # [T, H, W] bool: the frames found so far (``run``'s masks)
        self._scene_maps: dict[tuple, tuple] = {}  # (frame, references) -> (maps or None, residual noise)

    def lookalike_surroundings(self, k: int, mask: np.ndarray) -> float:
        """The share of the band around prompt k's ``mask`` (as wide as half the object,
        off the person) that the prompt's own colour model calls object (probability >
        0.5): near 0 for an object that stands out, a quarter for a transparent bottle
        on a grey floor, whose track then stays on the floor."""
        off = None if self.human_probs is None else self.human_probs[k] > 127
        return self._lookalike_share(self.appearance[k][0], k, mask, off)

    def person_lookalike(self, k: int, mask: np.ndarray) -> float:
        """The share of the person's pixels on prompt k's frame (off its ``mask``, by a few
        pixels) that the prompt's own colour model calls object (probability > 0.5): 0.25
        for a white racket held in front of a white shirt, under 0.2 for objects whose
        colours are not the person's clothes' (``LIKE_PERSON_SHARE``); 0 without person
        masks."""
        if self.human_probs is None:
            return 0.0
        person, like = self._person_and_lookalike(k, mask)
        if not person.any():
            return 0.0
        return float(like[person].mean())

    def _person_and_lookalike(self, k: int, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """([H, W] bool: the person's pixels on prompt k's frame off its ``mask`` by a few
        pixels, [H, W] bool: the pixels the prompt's own colour model calls object)."""
        import cv2

        person = (self.human_probs[k] > 127) & ~(cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0)
        return person, self.appearance[k][0].prob(self.images[k]) > 0.5

    def coloured_like_person(self, t: int, direction: int) -> bool:
        """Whether a pass from frame t towards ``direction`` looks for an object coloured
        like the person's clothes (``LIKE_PERSON_SHARE``): as the prompts either side of the
        frames it covers show the object, the nearest one on each side (the one side beyond
        the first or last prompt). A prompt shows the object as it looks there: a face-on
        racket's strings show the court rather than white, a transparent bottle in front
        of a black shirt shows the shirt; a prompt elsewhere in the clip says nothing about
        these frames."""
        lo, hi = sorted((t, t + direction))
        either = [max((k for k in self.prompts if k <= lo), default=None), min((k for k in self.prompts if k >= hi), default=None)]
        return max((self.like_person[k] for k in either if k is not None), default=0.0) >= LIKE_PERSON_SHARE

    def limbs_told_apart(self, k: int, mask: np.ndarray) -> tuple[str, ...]:
        """The kinds of limb (``limb_regions``) whose pixels on prompt k's frame (the
        person's, off its ``mask`` by a few pixels) the prompt's own colour model calls
        object (probability > 0.5) less than ``TOLD_APART_SHARE`` of the time, from at
        least ``MIN_LIMB_PIXELS`` of them: in front of those (a white racket before black
        shorts) the object can be told from the person. () without person masks or
        keypoints."""
        if self.human_probs is None or self.kp2d is None:
            return ()
        person, like = self._person_and_lookalike(k, mask)
        told = []
        for kind, region in limb_regions(self.kp2d[k], mask.shape).items():
            seen = like[person & region]
            if len(seen) >= MIN_LIMB_PIXELS and float(seen.mean()) < TOLD_APART_SHARE:
                told.append(kind)
        return tuple(told)

    def _person(self, t: int) -> np.ndarray:
        """[H, W] bool: the person's mask on frame t or, where MediaPipe found nobody there
        (a body dropped from a hand), on the nearest frame within two that has one."""
        T = len(self.images)
        for u in sorted(range(max(0, t - 2), min(T, t + 3)), key=lambda u: abs(u - t)):
            person = self.human_probs[u] > 127
            if person.any():
                return person
        return self.human_probs[t] > 127

    def _hidden_on_person(self, t: int) -> np.ndarray:
        """[H, W] bool: the person's pixels on frame t that the body covers
        (``body_regions``, the limbs told apart left out; all of them where its torso is not
        seen or it covers under ``BODY_COVER`` of them): in front of those, an object
        coloured like the person's clothes cannot be told from them. What the person's mask
        takes in beyond the body (a racket held out beside the legs) can."""
        if self._hidden is not None and self._hidden[0] == t:
            return self._hidden[1]  # asked again within a frame's step (the search, then its find)
        person = self._person(t)
        body = None if self.kp2d is None else body_regions(self.kp2d[t], person.shape)
        if body is None or (person & body).sum() < BODY_COVER * person.sum():
            hidden = person  # the landmarks do not say where the body is (a seated, half-hidden person)
        elif self.limbs_apart:
            hidden = person & body_regions(self.kp2d[t], person.shape, leave_out=self.limbs_apart)
        else:
            hidden = person & body
        self._hidden = (t, hidden)
        return hidden

    def on_person(self, t: int, mask: np.ndarray) -> bool:
        """Whether frame t's ``mask`` lies mostly (``ON_PERSON_SHARE``) on the person's
        body (``_hidden_on_person``)."""
        if self.human_probs is None or not mask.any():
            return False
        return float(self._hidden_on_person(t)[mask].mean()) >= ON_PERSON_SHARE

    def unclear(self, t: int, mask: np.ndarray) -> bool:
        """Whether frame t's ``mask`` cannot be told from what surrounds it: at least
        ``UNCLEAR_SHARE`` of the band around it (as wide as half the object; the hands,
        which hold it, left out) looks like the object under the prompt's own colour
        model. Then the mask is either a piece of a larger look-alike region (the patch
        of floor a transparent bottle was lifted off, where the track stayed) or a
        fraction of the object, the rest of it just outside; neither should teach the
        object branch."""
        if not mask.any():
            return False
        off = None if self.kp2d is None else hand_regions(self.kp2d[t], mask.shape)
        return self._lookalike_share(self.base_model, t, mask, off) >= UNCLEAR_SHARE

    def shows_the_scene(self, t: int, masks: np.ndarray, conf: np.ndarray) -> bool:
        """Whether frame t's mask (``masks`` [T, H, W] bool, ``conf`` [T]) shows the room
        rather than the object: at least ``SCENE_SHARE`` of its pixels seen in the nearest
        ``SCENE_REFS`` frames whose own found masks (above ``UNCLEAR_CONFIDENCE``) lie
        farther than the object's size from it show there what this frame shows: the median
        over those frames of ``StaticScene.residual`` (the person left out of them and of
        this frame) at most ``SCENE_TOL`` grey levels. No such frame, or too few of the
        mask's pixels seen off the person (``SCENE_SEEN``): False."""
        mask = masks[t]
        if self.scene is None or not mask.any():
            return False
        # Only pixels off this frame's person can be the room: behind a mask on the body lies
        # the person, whom the other frames' static scene leaves out (and where MediaPipe's mask
        # bleeds past the shirt, a dark shirt seen through a transparent bottle matches it).
        off_person = person_free(self.human_probs[t], self.scene.margin)[mask]
        if off_person.mean() < SCENE_SEEN:
            return False  # a held object mostly is: no frame needs comparing
        ys, xs = np.nonzero(mask)
        near = grown(mask, int(max(np.ptp(xs), np.ptp(ys))) + 1)
        nearest_first = sorted(range(len(masks)), key=lambda u: (abs(u - t), u))
        refs = list(itertools.islice((u for u in nearest_first if u != t and conf[u] > UNCLEAR_CONFIDENCE
                                      and masks[u].any() and not (masks[u] & near).any()), SCENE_REFS))
        if not refs:
            return False
        # Each frame alone, then their median: one whose mask missed the object (so that the
        # object, unmasked there, passes for room) cannot make the object room by itself.
        each = np.stack([self.scene.residual(t, [(u, masks[u])])[mask] for u in refs])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a pixel no frame sees stays NaN
            r = np.nanmedian(each, axis=0)
        seen = np.isfinite(r) & off_person
        if seen.mean() < SCENE_SEEN:
            return False
        return float((r[seen] <= SCENE_TOL).mean()) >= SCENE_SHARE

    def _lookalike_share(self, model: ColourModel, t: int, mask: np.ndarray, off: np.ndarray | None) -> float:
        """The share of the band around frame t's ``mask`` (half the object wide, minus
        ``off`` [H, W] bool) that ``model`` calls object (probability > 0.5); 0 for no band."""
        import cv2

        _, size = mask_stats(mask)
        r = max(3, int(0.5 * float(size.max())))
        ys, xs = np.nonzero(mask)
        H, W = mask.shape
        y0, y1, x0, x1 = max(0, ys.min() - r), min(H, ys.max() + r + 1), max(0, xs.min() - r), min(W, xs.max() + r + 1)
        m = mask[y0:y1, x0:x1]
        band = (cv2.dilate(m.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0) & ~m
        if off is not None:
            band &= ~off[y0:y1, x0:x1]
        if not band.any():
            return 0.0
        return float((model.prob(self.images[t, y0:y1, x0:x1])[band] > 0.5).mean())

    def use(self, k: int) -> None:
        """Track from prompt k: its colour model, colour evidence, area, size and shape."""
        self.base_model, self.ref_score, self.ref_area, self.convex, self.s0 = self.appearance[k]

    # -- models -----------------------------------------------------------------------

    def _adapted(self, t: int, mask: np.ndarray) -> ColourModel:
        """The prompt's colour model with a share ``adapt`` of frame t's object colours."""
        import cv2

        if self.adapt <= 0:
            return self.base_model
        ring = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8), iterations=3) > 0
        return self.base_model.blend(ColourModel.fit(self.images[t], mask, ~ring, self.distractors), self.adapt)

    def _local_model(self, st: _State) -> ColourModel:
        """The object's colours against its surroundings (a band of 0.4 x its size around
        it, hands and all) in the last frame it was found; the person's colours weigh in
        as in the prompt's model."""
        r = max(8, int(0.4 * float(st.size.max())))
        x0, y0, x1, y1 = window(st.mask, 1.0)
        band = np.zeros_like(st.mask)
        band[y0:y1, x0:x1] = grown(st.mask[y0:y1, x0:x1], r)
        return ColourModel.fit(self.images[st.t], st.visible, band & ~st.visible, self.distractors)

    def _static_and_moving(self, t: int, direction: int, last: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
        """(static [H, W] bool: pixels that show the static scene, moving [H, W] bool: pixels
        that clearly do not) in frame t, judged against the frames the pass came through
        where the object was found (its masks are known there, so a resting object is not
        taken for scene): those 1-12 frames back (``_SCENE_OFFSETS``), and where none is
        within ``LOST_REFS`` frames and their warp failed (``WARP_NOISE``), the frames in
        between without the object's mask too; None without person masks or frames that
        found it. ``last``: against the last frame the pass found the object
        in, for when none lies at those offsets (``_step`` rules the static scene out of
        the colour search with it).

        The thresholds follow the frame's own residual noise off the person: most pixels
        there are static scene.
        """
        if self.scene is None:
            return None
        T = len(self.images)
        if last:
            u = next((u for u in range(t - direction, -1 if direction > 0 else T, -direction) if self.masks[u].any()), None)
            refs = () if u is None else (u,)
        else:
            refs = tuple(u for u in (t - k * direction for k in _SCENE_OFFSETS) if 0 <= u < T and self.masks[u].any())
        maps, noise = self._scene_maps_against(t, refs)
        if not last and refs and min(abs(u - t) for u in refs) > LOST_REFS and (maps is None or noise > WARP_NOISE):
            # Lost over the last frames, and the frames that found it are too far for the
            # warp (the camera has moved on): the frames it was lost in are judged too, the
            # person alone left out of them (what the object was behind, or where it has left).
            maps, _ = self._scene_maps_against(t, refs + tuple(u for u in (t - k * direction for k in range(1, LOST_REFS + 1)) if 0 <= u < T))
        return maps

    def _scene_maps_against(self, t: int, refs: tuple[int, ...]) -> tuple[tuple[np.ndarray, np.ndarray] | None, float]:
        """``_static_and_moving``'s maps against the frames ``refs`` (each with its object
        mask where the pass found it) and the residual noise they were thresholded with."""
        key = (t, refs)
        if key not in self._scene_maps:
            maps, noise = None, float("inf")
            if refs:
                r = self.scene.residual(t, [(u, self.masks[u] if self.masks[u].any() else None) for u in refs])
                seen = np.isfinite(r)
                calib = seen & person_free(self.human_probs[t], self.scene.margin)
                if calib.sum() >= 0.1 * r.size:
                    noise = float(np.percentile(r[calib], 95))
                    lo = max(8.0, 3.0 * noise)
                    log.debug("scene residual frame %d: noise %.1f", t, noise)
                    maps = (seen & (r <= lo), seen & (r >= 2.5 * lo))
            self._scene_maps[key] = (maps, noise)
        return self._scene_maps[key]

    def resemblance(self, t: int, mask: np.ndarray) -> float:
        """How much frame t's ``mask`` still looks like the prompt's object: its mean
        probability under the prompt's own colour model (never adapted to later frames)
        over the prompt's, clipped to [0, 1]. A track that drifted onto the scene or the
        person through frames each a little like the last (the patch of floor a bottle
        was lifted off, a shoe beside a ball) keeps its adapted model's trust but loses
        this; the frame's confidence is capped by it."""
        if not mask.any():
            return 0.0
        ys, xs = np.nonzero(mask)
        y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
        score = float(self.base_model.prob(self.images[t, y0:y1, x0:x1])[mask[y0:y1, x0:x1]].mean())
        return float(np.clip(score / max(self.ref_score, 1e-6), 0.0, 1.0))

    def _hand_path(self, t0: int, t1: int, reach: float) -> np.ndarray | None:
        """[H, W] bool: the pixels within ``reach`` of a visible hand on any frame from t0 to
        t1 (either order), or None when no hand is visible on them."""
        import cv2

        H, W = self.images.shape[1:3]
        out = np.zeros((H, W), np.uint8)
        r = max(1, int(round(reach)))
        any_hand = False
        for u in range(min(t0, t1), max(t0, t1) + 1):
            for h in (0, 1):
                if _visible(self.hands, u, h):
                    x, y = (int(round(v)) for v in self.hands[u, h, :2])
                    cv2.circle(out, (x, y), r, 1, thickness=-1)
                    any_hand = True
        return out > 0 if any_hand else None

    def _hands_mask(self, t: int) -> np.ndarray:
        if self.kp2d is None:
            return np.zeros(self.images.shape[1:3], bool)
        return hand_regions(self.kp2d[t], self.images.shape[1:3])

    def _feet_mask(self, t: int) -> np.ndarray:
        if self.kp2d is None:
            return np.zeros(self.images.shape[1:3], bool)
        return foot_regions(self.kp2d[t], self.images.shape[1:3])

    def _off_the_feet(self, t: int, seg: np.ndarray, fitted: np.ndarray) -> np.ndarray:
        """GrabCut's outline ``seg`` [H, W] bool in frame t without what it added on a foot
        beyond the ``fitted`` shape (``FOOT_MARGIN`` of its size around it) -> [H, W] bool.
        A kicked ball touches the shoe it was kicked off, often in the same colours, and
        GrabCut spreads from the fitted ball into it."""
        if not seg.any():
            return seg
        import cv2

        feet = self._feet_mask(t)
        if not (seg & feet).any():
            return seg
        c, s = mask_stats(fitted)
        r = max(1, int(round(FOOT_MARGIN * float(s.max()))))
        near = cv2.dilate(fitted.astype(np.uint8), disk(r)) > 0
        out = seg & ~(feet & ~near)
        return fill_holes(largest_component_near(out, tuple(c))) if out.any() else out

    # -- passes -----------------------------------------------------------------------

    def run(self, start: int, direction: int, masks: np.ndarray, conf: np.ndarray, cues: list, fill: bool = False, on_frame=None,
            stop: int | None = None, carry_trust: bool = True) -> None:
        """Track from frame ``start`` (its mask known) towards ``direction`` (+1 or -1),
        writing ``masks``, ``conf`` and ``cues`` in place, up to the clip's end or frame
        ``stop`` (not included). ``fill``: only into empty frames, stopping at the first
        frame already found or where the object is lost. The passes from a prompt's frame
        share what they learn of its carrying hand (``carried_from``); the others (into a
        gap, or back from a clear find) never start on one. ``carry_trust``: a find a hand
        carries on from the frame before keeps that frame's confidence
        (``CARRIED_TRUST_CUES``); off for a pass that checks another's frames
        (``cross_check``), where trust handed on from its start is no evidence."""
        T = len(self.images)
        from_prompt = not fill and start in self.prompts
        self.colours_of_person = self.coloured_like_person(start, direction)
        if masks is not self.masks:
            self._scene_maps = {}  # judged against another pass's frames
        self.masks = masks
        m0 = masks[start]
        c0, s0 = mask_stats(m0)
        model = self._adapted(start, m0)
        st = _State(c0, np.zeros(2), s0, m0, m0, start, float(model.prob(self.images[start])[m0].mean()), float(m0.sum()))
        self.bank.forget(lambda u: False)
        self.bank.add(start, m0)
        if not fill:
            # A prompt in a hand's grip is carried by that hand from the start: the
            # search keeps to it and the hand cue may find it (a transparent bottle, whose
            # colours are whatever is behind it, has little else to go by).
            st.carrier = holding_hand(self.kp2d, start, m0)
            if st.carrier is None and from_prompt and start in self.carried_from:
                # A pass from this prompt the other way saw a hand carry it from the
                # prompt on: the hand's points are too rough to tell that on the prompt's
                # own two frames (a box held by its far side, the wrist 20 px off it), so
                # this pass inherits the carry.
                st.carrier = self.carried_from[start]
            st.carried = 0 if st.carrier is None else 2
            st.held = st.carried >= 2  # in a hand's grip: searched for where a hand has been (``HAND_PATH_REACH``)
        else:
            # A pass into a gap starts where the object was found again: at a hand, it is
            # searched for where a hand has been, from its first frame on.
            st.into_gap = True
            st.held = self._near_a_hand(start, m0, 0.5 * float(np.sqrt(m0.sum())))

        def undo(st: _State, t_end: int) -> tuple[_State, ColourModel]:
            """Drop a tentative hand find and what followed it, up to frame t_end."""
            t_h, _, st_before, model_before = st.pending
            for u in range(t_h, t_end, direction):
                masks[u], conf[u], cues[u] = False, 0.0, ""
            self.bank.forget(lambda u: (u - t_h) * direction < 0)
            st_before.lost += abs(t_end - t_h)
            return st_before, model_before

        t = start + direction
        unbroken = True  # found in every frame since the prompt
        while 0 <= t < T and t != stop and not (fill and masks[t].any()):
            f = self._step(t, st, direction, model)
            neg = self.negatives.get(t)
            if neg is not None and (f.visible & neg).any():  # never the object on this frame, whatever a cue found
                f.visible, f.extent = f.visible & ~neg, f.extent & ~neg
                if not f.visible.any():
                    f = _Found(f.visible, f.extent)
            if st.pending is not None and f.cue != "hand":
                # A find by the hand cue alone is tentative: the next frame, found without
                # the hand's help, must show the object carried by that hand, or both go.
                hand = st.pending[1]
                if not (f.visible.any() and st.t == t - direction and self._confirms_carry(st.t, t, st.mask, f.extent, hand)):
                    st, model = undo(st, t)
                    f = _Found(np.zeros_like(f.visible), np.zeros_like(f.visible))
                st.pending = None
            if fill and not f.visible.any():
                break
            if self.convex and f.extent.any():  # one convex piece (a ball, a box, a bottle)
                f.extent = drop_stray_pieces(f.extent, st.area)
                f.visible = f.visible & f.extent
            c = min(f.confidence, self.resemblance(t, f.visible))
            if carry_trust and f.cue in CARRIED_TRUST_CUES and st.carried >= 2 and st.t == t - direction:
                # Carried on from the frame before: the trust it was carried with, where its
                # colours no longer resemble the prompt's (``CARRIED_TRUST_CUES``).
                c = min(f.confidence, max(c, conf[st.t]))
            if self.unclear(t, f.visible):
                c = min(c, UNCLEAR_CONFIDENCE)
            masks[t], conf[t], cues[t] = f.visible, c, f.cue
            if f.visible.any():
                model = self._update(st, t, direction, f, model)
                if (from_prompt and unbroken and f.cue != "hand" and st.carried >= 2 and abs(t - start) <= st.carried + PROMPT_CARRY_SLACK
                        and self._near_a_hand(start, m0, HAND_NEAR * float(s0.max()), which=(st.carrier,))):
                    self.carried_from.setdefault(start, st.carrier)  # carried from (nearly) the prompt on
            else:
                unbroken = False
                st.centre = st.centre + st.velocity
                st.velocity = 0.5 * st.velocity  # a hidden object's motion is unknown
                st.lost += 1
            if on_frame:
                on_frame()
            t += direction
        if st.pending is not None:  # the clip ended before any confirmation
            undo(st, t)

    def _update(self, st: _State, t: int, direction: int, f: _Found, model: ColourModel) -> ColourModel:
        """Fold frame t's find into the state; returns the colour model for the next frame."""
        if f.cue == "hand" and st.pending is None:
            st.pending = (t, st.carrier, copy.deepcopy(st), model)
        carrier = carrying_hand(self.hands, st.t, t, st.mask, f.extent) if st.t == t - direction else None
        if carrier is not None:
            # Passed to the other hand (or the pose model swapped left and right), it is
            # still carried.
            st.carried = st.carried + 1 if carrier == st.carrier or st.carried >= 2 else 1
            st.carrier = carrier
        elif f.confidence >= 0.8 and not self._near_a_hand(t, f.extent, HAND_NEAR * float(mask_stats(f.extent)[1].max())):
            st.carrier, st.carried = None, 0  # clearly seen, and away from the hands
        c, s = mask_stats(f.visible)
        st.velocity = 0.5 * st.velocity + 0.5 * (c - st.centre) / (st.lost + 1)
        st.centre = c
        if f.cue != "hand" and (f.cue != "colour" or f.colour >= 0.8 * self.ref_score):
            # Only clear views update the size; occluded views would shrink it.
            st.size = np.clip(0.7 * st.size + 0.3 * s, 0.5 * self.s0, 2.0 * self.s0)
        if f.confidence >= 0.8:
            st.area = 0.7 * st.area + 0.3 * float(f.extent.sum())
        st.lost = 0
        st.held = st.carried >= 2
        st.mask, st.visible, st.t, st.colour = f.extent, f.visible, t, f.colour
        if self.colours_of_person:
            st.off_person = f.kept_on_person or not self.on_person(t, f.visible)
        self.bank.add(t, f.visible)
        if self.colours_of_person and f.colour < self.min_score * self.ref_score:
            # Found by its motion alone (at a hand, or fitted on from there): a racket's
            # outline with the scene seen through its strings or blurred into its swing. The
            # colour search, its only way back onto it beside the body, would learn the
            # scene's colours from it (the tennis clip's racket lost at 37-42 after 29-32).
            return model
        return self._adapted(t, f.visible)

    def _near_a_hand(self, t: int, mask: np.ndarray, reach: float, which: tuple = (0, 1)) -> bool:
        """Whether a visible hand (of ``which``) in frame t lies within ``reach`` pixels of ``mask``."""
        if self.hands is None or not mask.any():
            return False
        return any(_visible(self.hands, t, h) and _distance_to(mask, self.hands[t, h, :2]) <= reach for h in which)

    def _background_off(self, mask: np.ndarray, frames: tuple[int, ...]) -> np.ndarray:
        """Pixels that can only be static scene: away from ``mask`` (7 px and more) and off
        the person in each of ``frames`` -> [H, W] bool."""
        import cv2

        static = ~(cv2.dilate(mask.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0)
        if self.human_probs is not None:
            for t in frames:
                static &= self.human_probs[t] <= 127
        return static

    def _confirms_carry(self, t0: int, t1: int, m0: np.ndarray, m1: np.ndarray, hand: int) -> bool:
        """Whether the object the hand cue found in frame t0 (``m0``), found again in frame
        t1 (``m1``), is carried by ``hand``: touching it and moving with it (loosely: an
        object turning in the hand moves its centre), and not staying put with the
        background (a piece of background beside the hand, which any motion cue follows
        perfectly; when the hand hardly moves either, nothing tells them apart and the
        find is dropped)."""
        import cv2

        if carrying_hand(self.hands, t0, t1, m0, m1, touch=0.35, moved_max=0.6) != hand:
            return False
        Hm = self.bank.background_motion(t0, t1, self._background_off(m0, (t0,)))
        if Hm is None:
            return True
        # Where m0 would be had it stayed with the background; m1 (partly hidden by the
        # hand, maybe) lying inside that means it did.
        H, W = m0.shape
        m0_bg = cv2.warpPerspective(m0.astype(np.uint8), Hm, (W, H), flags=cv2.INTER_NEAREST)
        m0_bg = cv2.dilate(m0_bg, np.ones((5, 5), np.uint8)) > 0
        return bool((m1 & m0_bg).sum() < 0.9 * m1.sum())

    def _unchanged(self, t: int, t_prev: int, mask: np.ndarray) -> bool:
        """Whether the pixels under ``mask`` in frame t are static background: frame
        t_prev, warped onto frame t by the background's motion, shows the same there
        (a carried object has moved in, so it differs; a patch of wall beside the hand
        does not, beyond what the warp leaves on the background around it)."""
        import cv2

        if not 0 <= t_prev < len(self.images):
            return False
        H, W = mask.shape
        static = self._background_off(mask, (t, t_prev))
        Hm = self.bank.background_motion(t_prev, t, static)
        if Hm is None:
            return False
        prev = cv2.warpPerspective(self.images[t_prev], Hm, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        diff = np.abs(self.images[t].astype(np.int16) - prev.astype(np.int16)).mean(-1)
        _, s = mask_stats(mask)
        r = max(5, int(0.5 * float(s.max())))
        ring = (cv2.dilate(mask.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0) & static
        if ring.sum() < 0.5 * mask.sum():
            return False  # too little background around to calibrate on
        return bool(np.median(diff[mask]) <= max(6.0, 2.0 * np.median(diff[ring])))

    # -- one frame --------------------------------------------------------------------

    def _step(self, t: int, st: _State, direction: int, model: ColourModel) -> _Found:
        """Frame t, the object last found in frame ``st.t``: the first cue that holds."""
        rgb = self.images[t]
        H, W = rgb.shape[:2]
        prob = model.prob(rgb)
        if self.kp2d is not None:
            suppress_head(prob, self.kp2d[t], st.centre)
        hp = None if self.human_probs is None else self.human_probs[t].astype(np.float32) / 255.0
        # The hands are next to a handled object all the time and look like a skin-coloured
        # one: they count 5x less in the colour search and are never the visible object.
        hands = self._hands_mask(t)
        prob_search = prob.copy()
        prob_search[hands] *= 0.2
        if self.colours_of_person and hp is not None:
            prob_search[self._hidden_on_person(t)] = 0.0  # its colours say nothing on the body
        hands_t = None if self.hands is None else self.hands[t]
        maps = self._static_and_moving(t, direction)
        if maps is None:
            # No frame at the offsets found it (lost for a while): the last one that did
            # still keeps the static scene out of the colour search below (a look-alike
            # painting on the wall); the other cues go on without a static scene, except
            # for an object coloured like the person, lost in front of the person rather
            # than hidden: what moves at a hand is judged against that last view.
            seen = self._static_and_moving(t, direction, last=True)
            if seen is not None:
                prob_search[seen[0]] = 0.0
                if self.colours_of_person:
                    maps = seen
        if maps is None:
            static, moving = np.zeros((H, W), bool), np.zeros((H, W), bool)
        else:
            static, moving = maps
            # What moved and is not the person (nor a hand) is the object, whatever its colour.
            moving = moving & (hp <= 0.5) & ~hands
        neg = self.negatives.get(t)
        if neg is not None:  # the user's "not the object" here: like static scene, never object
            static, moving = static | neg, moving & ~neg
        prob_search[static] = 0.0  # the static scene is never the object
        # A carried object stays with its hand (a look-alike across the room is not it):
        # the search keeps to the hand, if visible, and near the motion prediction.
        # Otherwise the whole frame is searched.
        if abs(t - st.t) > self.max_hand_frames and not self.colours_of_person:
            st.carrier, st.carried = None, 0  # lost too long: it may have left the hand
        # An object coloured like the person is not looked for across the room either
        # (white court lines, a white caption): near the hands and the prediction only.
        floor = 0.0 if self.colours_of_person else 0.35
        if st.carried >= 2:
            floor = 0.0
            hands_t = self.hands[t, [st.carrier]] if _visible(self.hands, t, st.carrier) else None

        def colour_of(m):
            return float(prob[m].mean()) if m.any() else 0.0

        def off_the_person(found: _Found) -> _Found:
            # An object coloured like the person's clothes is not told from them: a find
            # lying on the person yields to what moves at a hand off it, or to nothing.
            if not (self.colours_of_person and self.on_person(t, found.visible)):
                return found
            if (found.cue in MOTION_CUES and st.t == t - direction and st.off_person
                    and found.confidence >= FIT_ON_PERSON):
                found.kept_on_person = True  # an arm swung across the object found beside the body
                return found
            at_hand = None if maps is None else self._moving_at_hands(t, st, moving, hands, prob)
            return _Found(np.zeros((H, W), bool), np.zeros((H, W), bool)) if at_hand is None else at_hand

        last_resort = None
        # 1. Motion.
        found = self._by_motion(t, st, direction, rgb, hp, hands, static, moving)
        if found is not None:
            found.colour = colour_of(found.visible)
            # It must still look like the object: clearly (half the prompt's evidence), or
            # keeping most of what it had (a turning object shows new faces gradually; a
            # fit that slid onto a hand or the background loses it at once) ...
            looks = found.colour >= self.min_score * self.ref_score or found.colour >= 0.6 * st.colour
            # A hand find awaiting confirmation shows a face no colour model knows: the
            # confirmation (carried by that hand, not staying with the background) judges
            # it, except for the placement the hand itself made, which moves with the
            # hand by construction.
            looks = looks or (st.pending is not None and found.cue != "carried")
            if not looks and found.visible.any() and (found.visible & moving).sum() >= MOVING_FIT_SHARE * found.visible.sum():
                # Turned to faces of other colours, but what it covers moves and is not the
                # person: kept in case neither the colour search nor the hand finds it.
                last_resort = found
            # ... and no clearly better-looking place elsewhere (the fit held on to a
            # look-alike while the object moved away, e.g. a hand after a bounce). A fit
            # lying mostly on the feet (white shoes a white ball was kicked off) yields to
            # any place elsewhere the colour search below would take.
            centre, score, _ = locate(prob_search, st, hands_t, floor)
            far = np.linalg.norm(centre - mask_stats(found.visible)[0]) > 0.5 * float(np.hypot(*st.size))
            better = far and score > 1.3 * found.colour and score >= self.min_score * self.ref_score
            feet = self._feet_mask(t)
            if not better and (found.visible & feet).sum() >= 0.5 * found.visible.sum():
                # Off the feet, the search counts them 5x less, like the hands.
                off_feet = prob_search.copy()
                off_feet[feet] *= 0.2
                centre, score, plausible = locate(off_feet, st, hands_t, floor)
                far = np.linalg.norm(centre - mask_stats(found.visible)[0]) > 0.5 * float(np.hypot(*st.size))
                better = far and score >= self.min_score * self.ref_score * (1.3 - 0.6 * plausible)
                if better:
                    prob_search = off_feet
            if looks and not better:
                return off_the_person(found)

        # 2. Colour search. The evidence needed falls with prior plausibility: min_score
        #    at a moderately likely place, 0.7x that where predicted or at a hand, 1.3x far
        #    from both. An object lost while carried is where a hand has been since. Lost
        #    for longer than a carry is kept (``max_hand_frames``), the discount lapses: the
        #    prediction's reach has grown over much of the frame and the object may have
        #    left the hand (a bookshelf's red and brown books, re-found at 0.42 of the
        #    prompt's evidence next to a hand after 12 frames lost behind the body, on the
        #    synthetic video at 60 frames, variant 1).
        if st.held and (st.into_gap or st.t != t - direction):
            path = self._hand_path(st.t, t, HAND_PATH_REACH * float(np.sqrt(max(st.area, 1.0))))
            if path is not None:
                prob_search = np.where(path, prob_search, 0.0)
        centre, score, plausible = locate(prob_search, st, hands_t, floor)
        need = 1.3 - 0.6 * plausible
        if st.lost > self.max_hand_frames:
            need = max(need, 1.0)
        if score >= self.min_score * self.ref_score * need:
            cf = min(1.0, score / self.ref_score)
            seg = grabcut_at(rgb, prob_search, centre, st.size, hp, static=static)
            seg = fill_holes(largest_component_near(seg, tuple(centre))) & ~hands if seg.any() else seg
            sized = 0.25 * self.ref_area <= seg.sum() <= MAX_AREA_GROWTH * self.ref_area
            if sized and not self.unclear(t, seg):
                return off_the_person(_Found(seg, seg, cf, "colour", score))
            # GrabCut leaked, collapsed, or cut a piece out of a look-alike whole (a quarter
            # of a ball, the rest around it): the probable pixels in the located window.
            yy, xx = np.mgrid[:H, :W]
            ell = ((xx + 0.5 - centre[0]) / (0.5 * st.size[0])) ** 2 + ((yy + 0.5 - centre[1]) / (0.5 * st.size[1])) ** 2
            fallback = (ell <= 1.0) & (prob_search > 0.5)
            if fallback.sum() >= 0.25 * self.ref_area:
                fallback = fill_holes(largest_component_near(fallback, tuple(centre))) & ~hands
                if not (sized and self.unclear(t, fallback)):
                    return off_the_person(_Found(fallback, fallback, cf, "colour", score))
            if sized:  # neither is clear: GrabCut's, for what it is worth (its confidence will say)
                return off_the_person(_Found(seg, seg, cf, "colour", score))

        # 3. The hand: an object carried for a while is still in that hand, whatever face
        #    it now shows (for a few frames; past them it may have been put down): what
        #    moves there and is not the person or, without a static scene to tell what
        #    moves, GrabCut next to the hand (which also takes a piece of background). An
        #    object coloured like the person is looked for at the hands carried or not
        #    (``_moving_at_hands`` says which it looks for).
        h = st.carrier
        if maps is not None:
            at_hand = self._moving_at_hands(t, st, moving, hands, prob)
            if at_hand is not None:
                return at_hand
        elif st.carried >= 2 and _visible(self.hands, t, h):
            seg = grabcut_at_hand(rgb, self.hands[t, h, :2], float(np.sqrt(st.area)), hp, static=static)
            visible = seg & ~hands
            if (0.4 * st.area <= visible.sum() <= 2.5 * st.area and solidity(seg) >= 0.8
                    and not self._unchanged(t, t - direction, visible)):
                return off_the_person(_Found(visible, visible, 0.3, "hand", colour_of(visible)))
        # 4. The motion fit that no longer looked like the object, where it moves.
        if last_resort is not None:
            last_resort.confidence = min(last_resort.confidence, 0.5)
            return off_the_person(last_resort)
        empty = np.zeros((H, W), bool)
        return _Found(empty, empty)

    def _moving_at_hands(self, t: int, st: _State, moving: np.ndarray, hands: np.ndarray, prob: np.ndarray) -> _Found | None:
        """Cue 3 with a static scene: what moves at the carrying hand (or the other one) and
        is not the person, if it is about the object's size; None otherwise.

        An object coloured like the person's clothes is looked for at either visible hand
        even where no carry was seen (the carrying hand first, if one was): the colour
        search skips the body for it, and a racket held by its handle is never seen
        carried, its head lying a handle's length from the palm (0.6-1.3 of its size on
        the tennis clip, where ``carrying_hand`` asks for 0.3). Only that clip's racket is
        coloured like the person among the development clips and the synthetic video
        (docs/experiments/2026-12-03-c-a-racket-found-where-it-moves-at-the-hand.md)."""
        h = st.carrier
        if st.carried < 2 and not self.colours_of_person:
            return None
        for k in ((0, 1) if h is None else (h, 1 - h)):
            if not _visible(self.hands, t, k):
                continue
            seg = moving_at_hand(moving, self.hands[t, k, :2], float(np.sqrt(st.area)), self.convex)
            visible = seg & ~hands
            if visible.sum() < 0.4 * st.area and self.colours_of_person:  # which implies person masks
                # Face-on over the banner a racket's head moves as a 1-2 px frame round strings
                # that show the banner.
                seg = moving_at_hand(moving, self.hands[t, k, :2], float(np.sqrt(st.area)), self.convex, self._person(t))
                visible = seg & ~hands
            if 0.4 * st.area <= visible.sum() <= 2.5 * st.area:
                return _Found(visible, visible, 0.5, "moving", float(prob[visible].mean()))
        return None

    def _by_motion(self, t: int, st: _State, direction: int, rgb: np.ndarray, hp, hands: np.ndarray,
                   static: np.ndarray, moving: np.ndarray) -> _Found | None:
        """Cue 1: the last extent placed by each motion hint, fitted to this frame's local
        colour likelihood; the best fit, if good enough, refined by GrabCut."""
        lp = self._local_model(st).prob(rgb)
        cands = [("stay", st.mask)]
        feat = self.bank.match(t)
        if feat is not None:
            cands.append(("features", feat[0]))
        kept = None
        if st.t == t - direction:
            flow, kept = warp_mask_by_flow(self.images[st.t], rgb, st.mask)
            if flow.sum() >= 0.25 * st.mask.sum():
                cands.append(("flow", flow))
            # Not while a hand find waits for confirmation: that must come without the hand.
            h = st.carrier
            if st.pending is None and st.carried >= 2 and _visible(self.hands, st.t, h) and _visible(self.hands, t, h):
                cands.append(("carried", move_with_hand(st.mask, self.kp2d[st.t], self.kp2d[t], h)))
        # Evidence beyond colour: what moves and is not the person is object, the static
        # scene never is.
        lp[moving] = np.maximum(lp[moving], 0.9)
        lp[static] = 0.0
        best = None
        for name, cand in cands:
            if cand.any():
                aligned, cc = align_mask(cand, lp)
                if aligned is not None and aligned.any() and (best is None or cc > best[2]):
                    best = (name, aligned, cc)
        if best is None or best[2] < self.min_align:
            return None  # moved too far, hidden, or changed too much
        cue, pred, cc = best
        seg = grabcut_from_seed(rgb, lp, pred, hp, static=static)
        seg = fill_holes(largest_component_near(seg, tuple(mask_stats(pred)[0]))) if seg.any() else seg
        seg = self._off_the_feet(t, seg, pred)
        if kept is not None:
            # What the rigid fit places on the object and the flow shows unchanged from
            # the object stays object: GrabCut cuts away faces coloured like what they are
            # held against, and a rigid object does not shrink.
            seg |= pred & kept & ~hands & ~static
        if not (seg.any() and iou(seg, pred) >= 0.5 and 0.5 <= seg.sum() / pred.sum() <= 2.0):
            seg = pred  # GrabCut wandered off: keep the fitted shape
        if (seg & ~hands).sum() < 0.25 * seg.sum():
            return None  # mostly hand: the fit slid onto the hand holding the object
        # Fingers in front of the object: the extent carries on to the next frame, the
        # visible mask leaves out hand pixels that do not look like the object.
        visible = seg & ~(hands & (lp < 0.5))
        cf = float(np.clip((cc - self.min_align) / (0.9 - self.min_align), 0.3, 1.0))
        return _Found(visible, seg, cf, cue)


def propagate_masks(
    images: np.ndarray,
    prompt_mask: np.ndarray | list[np.ndarray],
    prompt_frame: int | list[int],
    human_probs: np.ndarray | None = None,
    kp2d: np.ndarray | None = None,
    min_score: float = 0.5,
    adapt: float = 0.1,
    min_align: float = 0.5,
    max_hand_frames: int = 4,
    cues: list | None = None,
    on_frame=None,
    negatives: dict[int, np.ndarray] | None = None,
    sources: list | None = None,
    lookalike: dict | None = None,
    still: dict | None = None,
    like_person: dict | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Propagate one frame's object mask, or several frames' masks, through the video (see
    the module docstring; several prompts: ``combine_passes``).

    images [T, H, W, 3] uint8; prompt_mask [H, W] bool at frame ``prompt_frame``, or a
    list of masks and a list of their frames (one per frame); human_probs [T, H, W] uint8
    person probabilities (optional prior); kp2d [T, 33, 3] MediaPipe keypoints (optional:
    the hands and the head); ``negatives`` {frame: [H, W] bool}: pixels that are not the
    object on that frame (never object there; their colours count against the object in
    every colour model).

    ``min_score``: a colour-search window whose mean object probability is below this
    fraction of the prompt mask's counts as "object not visible" (0.7x that where the
    motion prediction or a hand puts the object, 1.3x far from both); a motion fit must
    keep this fraction, or 0.6 of what it had in the last frame. ``adapt``: share of the
    last found mask's colours in the colour model. ``min_align``: the least correlation
    of a motion fit. ``max_hand_frames``: how many frames after losing a carried object
    the hand cue looks for it. ``cues``: a list that receives the cue that found each
    frame ("prompt", "stay", "features", "flow", "carried", "colour", "hand" or "").
    ``sources``: a list that receives the prompt frame each frame's result comes from.
    ``lookalike``: a dict that receives, per prompt frame, the share of the prompt's
    surroundings that looks like the object (``_Tracker.lookalike_surroundings``).
    ``like_person``: a dict that receives, per prompt frame, the share of the person's
    pixels that look like the object (``_Tracker.person_lookalike``; from
    ``LIKE_PERSON_SHARE`` on, the object is only looked for off the person's body).
    ``still``: a dict that receives, per prompt frame, how many pixels of the prompt's mask
    were left out as still scene (``without_still_parts``), and per other frame where
    some were, how many of its mask.

    Returns (masks [T, H, W] bool, confidence [T] in [0, 1]; 0 where the object was lost).
    """
    T, H, W, _ = images.shape
    if isinstance(prompt_frame, (list, tuple)):
        prompts = {int(k): np.asarray(m, bool) for k, m in zip(prompt_frame, prompt_mask)}
        assert len(prompts) == len(prompt_frame) == len(prompt_mask), "one prompt per frame"
    else:
        prompts = {int(prompt_frame): prompt_mask}
    frames = sorted(prompts)
    for k in frames:
        assert 0 <= k < T, f"prompt frame {k} outside 0..{T - 1}"
        if not prompts[k].any():
            raise UserError(f"the object prompt on frame {k} gave an empty mask")
    masks = np.zeros((T, H, W), bool)
    conf = np.zeros(T)
    found = [""] * T
    origin = [frames[0]] * T
    way = np.where(np.arange(T) > frames[-1], 1, -1)  # the direction each frame was tracked in
    tracker = _Tracker(images, None, None, human_probs, kp2d, min_score, adapt, min_align, max_hand_frames,
                       prompts=prompts, negatives=negatives)
    prompts = tracker.prompts
    if still is not None:
        still.update(tracker.still_px)
    for k in frames:
        masks[k], conf[k], found[k], origin[k] = prompts[k], 1.0, "prompt", k
        if lookalike is not None:
            lookalike[k] = tracker.lookalike_surroundings(k, prompts[k])
        if like_person is not None:
            like_person[k] = tracker.like_person[k]
    done = [len(frames)]
    # The bar counts every frame a pass tracks (the frames between two prompts twice, once
    # from each, and the prompts they reach), and each frame an outline is fitted to between
    # two prompts (``bridge``, and where it fails ``lone_pass`` from either) or beyond the
    # first and the last (``lone_pass``): it shows their sum as a share of the frames, and
    # never goes back. A lone pass counts the frames it did not reach as fitted; following
    # its frames back (``outline.returns``) is not counted.
    pairs = list(zip(frames[:-1], frames[1:]))
    ends = ((frames[0], 0), (frames[-1], T - 1))  # beyond the first prompt and the last
    twice = sum(b - a + 1 for a, b in pairs)
    outline_total = 0 if kp2d is None else sum(4 * (b - a) - 2 for a, b in pairs if b - a >= 2) + sum(abs(e - k) for k, e in ends)
    outlined = [0]

    def report():
        if on_frame:
            on_frame(min(int((done[0] + outlined[0]) * T / (T + twice + outline_total)), T))

    def tick():
        done[0] += 1
        report()

    def outline_tick():
        outlined[0] += 1
        report()

    report()

    def fill_gaps(m, c, cu, start: int, direction: int, end: int, w: np.ndarray) -> None:
        # Back into each gap from where the object was found again (it reappeared with a
        # face or at a place the pass through the gap could not connect to).
        for t in range(start + direction, end, direction):
            if m[t].any() and not m[t - direction].any():
                unfound = [not x for x in cu]  # a frame the pass finds gets its cue
                tracker.run(t, -direction, m, c, cu, fill=True)
                w[[u for u in range(T) if unfound[u] and cu[u]]] = -direction  # tracked back from t

    # Between two prompts: a pass from each towards the other, each reaching the other's
    # frame; the frames between take one or the other (``combine_passes``). And the two
    # prompts' outlines, followed by their edges, where they meet in a hand (``bridge``).
    bridges = []
    lone = []  # (prompt, its lone pass): applied at the end

    def lone_from(k: int, stop: int) -> None:
        # The way back is checked only where it can give frames: an object coloured like
        # the person, which the colour cues do not look for on the person.
        before = outlined[0]
        like = tracker.coloured_like_person(k, 1 if stop > k else -1)
        shapes = lone_pass(images, prompts[k], k, stop, kp2d, on_frame=outline_tick, check_back=like) if stop != k else None
        outlined[0] = before + abs(stop - k)  # the frames a pass did not reach count as fitted
        report()
        if shapes:
            lone.append((k, shapes))

    for a, b in pairs:
        if kp2d is not None and b - a >= 2:
            bridged = bridge(images, prompts[a], a, prompts[b], b, kp2d, on_frame=outline_tick)
            if bridged is not None:
                bridges.append((a, b, *bridged))
                outlined[0] += 2 * (b - a - 1)  # no lone passes between them
            else:  # each prompt's outline alone, towards the other
                lone_from(a, b - 1)
                lone_from(b, a + 1)
        passes = []
        for k, direction, stop in ((a, +1, b + 1), (b, -1, a - 1)):
            m, c, cu, w = np.zeros((T, H, W), bool), np.zeros(T), [""] * T, np.full(T, direction)
            m[k], c[k], cu[k] = prompts[k], 1.0, "prompt"
            tracker.use(k)
            tracker.run(k, direction, m, c, cu, stop=stop, on_frame=tick)
            fill_gaps(m, c, cu, k, direction, stop, w)
            passes.append((m, c, cu, w))
        (ma, ca, cua, wa), (mb, cb, cub, wb) = passes
        switch = combine_passes(ma[a : b + 1], mb[a : b + 1]) + a
        second = beyond_the_switch(ma[a : b + 1], mb[a : b + 1], switch - a)
        log.debug("prompts %d and %d: frames from %d on take the second's pass", a, b, switch)
        for t in range(a + 1, b):
            src = (mb, cb, cub, b, wb) if second[t - a] else (ma, ca, cua, a, wa)
            masks[t], conf[t], found[t], origin[t], way[t] = src[0][t], src[1][t], src[2][t], src[3], src[4][t]
    # Beyond the first prompt and the last, each one's outline alone (``lone_pass``).
    for k, end in ends if kp2d is not None else ():
        lone_from(k, end)
    # Before the first prompt and after the last: that prompt's pass, as with one prompt.
    for k, direction in ((frames[-1], +1), (frames[0], -1)):
        tracker.use(k)
        tracker.run(k, direction, masks, conf, found, on_frame=tick)
    for k, direction in ((frames[-1], +1), (frames[0], -1)):
        tracker.use(k)
        fill_gaps(masks, conf, found, k, direction, T if direction > 0 else -1, way)
    for t in list(range(frames[-1] + 1, T)) + list(range(frames[0])):
        origin[t] = frames[-1] if t > frames[-1] else frames[0]
    cross_check(tracker, masks, conf, found, origin, way)
    for a, b, shapes, switch, agree in bridges:
        # A frame the colour cues saw clearly keeps its mask, and one they lost stays lost
        # (hidden, for all a followed outline can tell); the others take the outline
        # where a hand holds it, or holds it on the frames either side: one frame's hand
        # points off the fingers is the pose model's jitter, not a hand letting go and
        # taking hold again (the bottle clip's frame 14 at 384 px: the outline on the
        # bottle, the hand's region beside it covering 0.07 of it, 0.15 and 0.57 either side).
        held = {t: holding_hand(kp2d, t, shape) is not None for t, shape in shapes.items()}
        took = [t for t in shapes if 0.0 < conf[t] < CLEAR_CONFIDENCE and (held[t] or (held.get(t - 1) and held.get(t + 1)))]
        for t in took:
            masks[t], conf[t], found[t], origin[t] = shapes[t], OUTLINE_CONFIDENCE, "outline", a if t <= switch else b
        log.info("prompts %d and %d: their outlines, followed by the image's edges, meet at frame %d (IoU %.2f) in a hand; "
                 "%d frame(s) between them take the outline", a, b, switch, agree, len(took))
    if kp2d is not None:
        # The arm that holds the object is not the object, whatever cue found it there.
        for t in np.flatnonzero(carried_on(on_forearm(masks, kp2d), masks, found)):
            if found[t] != "prompt":
                conf[t] = min(conf[t], UNCLEAR_CONFIDENCE)
    # A find that shows what the room shows there while the object is elsewhere (each
    # frame judged against the others' confidences as the passes left them).
    scenery = [t for t in range(T) if found[t] != "prompt" and conf[t] > UNCLEAR_CONFIDENCE and tracker.shows_the_scene(t, masks, conf)]
    if scenery:
        log.info("the object masks of frame(s) %s show the room as other frames see it there, with the object elsewhere: "
                 "they do not supervise it", scenery)
        conf[scenery] = UNCLEAR_CONFIDENCE
    # What a frame's outline took in of the room around the object (a GrabCut spreading
    # into the bed beside a guitar), where the rest of the mask moves.
    if tracker.scene is not None:
        for t in range(T):
            if masks[t].any() and found[t] != "prompt":
                kept = without_still_parts(images[t], masks[t], tracker.scene, t)
                if still is not None and kept.sum() < masks[t].sum():
                    still[t] = int(masks[t].sum() - kept.sum())
                masks[t] = kept
    grown = too_large(masks, found, origin, {k: tracker.appearance[k][2] for k in frames})
    conf[grown] = np.minimum(conf[grown], UNCLEAR_CONFIDENCE)
    if len(grown):
        log.info("the object masks of frame(s) %s are over %gx their prompt's area: the track spread onto what lies next to "
                 "the object; they do not supervise it", grown.tolist(), MAX_AREA_GROWTH)
    # A lone outline gives the frames the colour cues lost or doubt, all their doubts
    # applied (``lone_outline_frames``); of two passes giving a frame (from the prompts
    # either side), the one from the nearer prompt. An outline on the arm is the arm.
    took = {}
    for k, shapes in lone:
        # The colour cues do not look for an object coloured like the person on the person
        # (a pass for another object has no frames that return).
        given = lone_outline_frames(k, shapes, masks, conf, shapes.held, shapes.returning, lambda t: tracker.on_person(t, shapes[t]))
        for t in given:
            if t not in took or abs(t - k) < abs(t - took[t][0]):
                took[t] = (k, shapes)
        if given:
            log.info("prompt %d: its outline, followed alone by the image's edges (checked by the hand holding it, or by "
                     "following it back), gives %d frame(s) %s it (%d-%d)",
                     k, len(given), "before" if given[0] < k else "after", min(given), max(given))
    for t, (k, shapes) in took.items():
        masks[t], conf[t], found[t], origin[t] = shapes[t], LONE_CONFIDENCE, "outline", k
    if took:
        arm = on_forearm(masks, kp2d)
        conf[[t for t in took if arm[t]]] = UNCLEAR_CONFIDENCE
    log.debug("object cues per frame: %s", found)
    if cues is not None:
        cues[:] = found
    if sources is not None:
        sources[:] = origin
    return masks, conf


def too_large(masks: np.ndarray, found: list, origin: list, prompt_area: dict, growth: float = MAX_AREA_GROWTH) -> np.ndarray:
    """The frames whose mask (``masks`` [T, H, W] bool) is more than ``growth`` times the
    area of the prompt it was tracked from (``origin`` [T] prompt frames; ``prompt_area``
    {prompt frame: pixels}); prompts (``found`` "prompt") never are -> [k] frame indices.
    See ``MAX_AREA_GROWTH``."""
    area = masks.reshape(len(masks), -1).sum(1)
    return np.array([t for t in range(len(masks)) if found[t] != "prompt" and area[t] > growth * prompt_area[origin[t]]], int)


def cross_check(tracker: "_Tracker", masks: np.ndarray, conf: np.ndarray, found: list, origin: list, way: np.ndarray) -> list[int]:
    """Track each run of doubtful frames again from its other side; where the two tracks
    disagree, keep the second's mask if it is clear, else mark the frame unclear -> the
    frames changed (``masks``, ``conf`` and ``found`` are updated in place).

    A doubtful frame was found with confidence below ``CLEAR_CONFIDENCE`` (not a prompt).
    A run of them, tracked forwards (``way`` +1, ``origin`` the prompt it came from), ends
    at a frame found clearly: a pass from that frame back through the run (with the same
    prompt's appearance) tracks the run from the side its own pass never saw; likewise
    for runs tracked backwards. Where both passes find something and their masks overlap
    by less than ``CROSS_AGREE`` (IoU), one of them left the object. The second pass's
    mask is kept where it found the object clearly (a ball kicked up faster than the
    flow: the forward track stays on the shoe, the pass back from the next clear view
    follows the ball). Where it found something less clearly but more surely than the
    first pass did, the frame's confidence falls to ``UNCLEAR_CONFIDENCE``. A frame the
    second pass loses, or finds less surely than the first (a pass that starts at a
    clear view can still fail at once), is left as it is. The second pass goes by its own
    fits: the trust a carry would hand on from its clear start is not evidence
    (``_Tracker.run``'s ``carry_trust``; on the guitar clip at 960 px it would have made
    frames 63-64, on the guitar, unclear).
    """
    T = len(masks)
    doubtful = (conf > 0) & (conf < CLEAR_CONFIDENCE) & np.array([f != "prompt" for f in found])
    changed = []
    m = None  # the second passes' masks: one array for all runs, cleared after each
    t = 0
    while t < T:
        if not doubtful[t]:
            t += 1
            continue
        a = t
        while t + 1 < T and doubtful[t + 1] and way[t + 1] == way[a] and origin[t + 1] == origin[a]:
            t += 1
        b, t = t, t + 1
        d = int(way[a])
        anchor = b + 1 if d > 0 else a - 1  # the clear frame at the run's far end
        if not (0 <= anchor < T) or conf[anchor] < CLEAR_CONFIDENCE or found[anchor] == "prompt":
            # No clear view there, or a prompt: between two prompts, the pass from each
            # is already weighed against the other's (``combine_passes``).
            continue
        stop = a - 1 if d > 0 else b + 1
        m = np.zeros_like(masks) if m is None else m
        c, cu = np.zeros(T), [""] * T
        m[anchor], c[anchor], cu[anchor] = masks[anchor], conf[anchor], found[anchor]
        tracker.use(origin[anchor])
        tracker.run(anchor, -d, m, c, cu, stop=stop, carry_trust=False)
        for u in range(a, b + 1):
            if m[u].any() and iou(m[u], masks[u]) < CROSS_AGREE:
                if c[u] >= CLEAR_CONFIDENCE:  # the second pass sees it clearly: its mask
                    masks[u], conf[u], found[u] = m[u], c[u], cu[u]
                elif c[u] > conf[u]:  # contradicted by a surer find: unclear
                    conf[u] = min(conf[u], UNCLEAR_CONFIDENCE)
                else:  # a less sure find says little against it
                    continue
                changed.append(u)
        m[a : b + 1], m[anchor] = False, False
    if changed:
        log.debug("object frames whose tracks from both sides disagree: %s", changed)
    return changed


def beyond_the_switch(forward: np.ndarray, backward: np.ndarray, switch: int, agree: float = 0.5) -> np.ndarray:
    """Which pass each frame between two prompts takes -> [n] bool, True for ``backward``:
    frames before ``switch`` (``combine_passes``) the forward pass, from it on the backward
    one, except beyond the reach of the pass a frame would take (it lost the object
    somewhere between its prompt and that frame) where the other pass, on the same object
    as it at the switch (mask IoU at least ``agree``), holds the object without a gap from
    the switch to that frame. A pass that goes on holding the object from where both
    agreed is as good as one from a prompt; the one beyond its reach found it again after
    losing it, or not at all. Where the switch lies within both passes' reach, nothing
    changes.

    On the tennis clip the forward pass held the racket from the switch (frame 40, IoU
    0.93) over the banner to frame 50, where the backward one had lost it from 59 down to
    45 (docs/experiments/2026-12-03-e-a-thin-racket-over-the-banner.md)."""
    n = len(forward)
    second = np.arange(n) >= switch
    if not 0 < switch < n or iou(forward[switch], backward[switch]) < agree:
        return second
    found_f, found_b, reach_f, reach_b = _reaches(forward, backward)
    t = switch + 1
    while t < min(reach_b, n - 1) and found_f[t]:  # forward on from the switch, beyond backward's reach
        second[t] = False
        t += 1
    t = switch - 1
    while t > max(reach_f, 0) and found_b[t]:  # backward on from the switch, beyond forward's reach
        second[t] = True
        t -= 1
    return second


def _reaches(forward: np.ndarray, backward: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(found_f, found_b, reach_f, reach_b) of two passes between prompts at frames 0 and
    n - 1: the frames each found, the last frame of the forward pass's unbroken run from 0
    and the first frame of the backward pass's unbroken run back from n - 1."""
    n = len(forward)
    found_f = forward.reshape(n, -1).any(1)
    found_b = backward.reshape(n, -1).any(1)
    reach_f = n - 1 if found_f.all() else int(np.argmin(found_f)) - 1
    reach_b = 0 if found_b.all() else n - int(np.argmin(found_b[::-1]))
    return found_f, found_b, reach_f, reach_b


def combine_passes(forward: np.ndarray, backward: np.ndarray, agree: float = 0.5) -> int:
    """Where to switch from one prompt's pass to the next's, between two prompts.

    ``forward`` [n, H, W] bool: the pass from the first prompt (frame 0 here) to the
    second (frame n - 1); ``backward``: the pass from the second back to the first.
    Returns s in [1, n - 1]: frames 1..s-1 take ``forward``, s..n-2 take ``backward``.

    A track that leaves the object (drifts to the shorts, or loses it) rarely comes back,
    so each pass is trusted from its prompt up to some frame and the switch belongs
    between those. Each pass *reaches* the frames it found without a gap from its prompt
    on; the switch is kept where both sides are within their reach. Inside that, it goes
    to the frame where the two passes agree best (mask IoU at least ``agree``): both are
    on the same object there and the switch shows no jump. Where they agree nowhere, it
    is the frame nearest the middle: the nearest prompt's pass.

    Not the more confident pass: the tracker's confidence says how well a fit matched its
    own colour model, and a track that drifted onto clothing matches the clothing well.
    ``agree`` 0.5 is set, not swept: it only separates two passes on the same object from
    passes on different things (docs/experiments/2026-11-25-several-prompts.md).
    """
    n = len(forward)
    assert n == len(backward) and n >= 2
    if n == 2:
        return 1
    _, _, reach_f, reach_b = _reaches(forward, backward)
    lo, hi = max(1, reach_b), min(n - 1, reach_f + 1)
    lo, hi = min(lo, hi), max(lo, hi)
    cand = np.arange(lo, hi + 1)
    mid = 0.5 * (n - 1)
    scores = np.array([iou(forward[t], backward[t]) for t in cand])
    # The best agreement (ties to the middle); otherwise the frame nearest the middle.
    key = [(-(sc if sc >= agree else 0.0), abs(t - mid), t) for t, sc in zip(cand, scores)]
    return int(min(key)[2])
