#!/usr/bin/env python3
"""A Python robot with its own place model, on the real Nordland data.

What a researcher does with fleetmem without touching C++:
  1. Robot "summer" drives the route in summer: computes codes with the
     user's model (here a linear encoder over patch-normalised thumbnails,
     in numpy), uploads them with their places, rewards and, as each trace's
     attachment, the observation's descriptor (the input of the model).
  2. Robot "winter" drives the first half of the route in winter and
     uploads its traces too; the second half is held out.
  3. Place recognition of the held-out winter frames against the fleet's
     memory, with the first model (recall@1 within +-2 frames, the data's
     rule).
  4. Replay: the winter robot streams batches of the fleet's memory
     (fleetmem.ReplayDataset: importance sampling, Eq. 18) into its training
     loop: a triplet loss pulling together descriptors of the same place
     seen in the two seasons.
  5. A new encoder version means a new fleet (a fleet holds one encoder
     version): every trace of the old fleet is exported, re-encoded from its
     attachment and uploaded to the new one; step 3 is repeated.

  nordland_robot.py --server 127.0.0.1:50051 --data-root ../shared/data
docs/python.md shows a run and what it printed.

Each run uses fleets of its own (nordland-py-<time>-v1 and -v2), so that a
second run measures its own traces; with --fleet NAME it stops if NAME-v1
or NAME-v2 exists already, unless --replace (which deletes them first: an
admin's right when the server has credentials).
"""

import argparse
import pathlib
import sys
import time

import numpy as np
from PIL import Image

import fleetmem

TOLERANCE = 20  # +-2 file names: the data's rule (10 route units apart)


def descriptor(path: pathlib.Path) -> np.ndarray:
    """512 numbers: the 64 x 32 grey frame averaged to 32 x 16, patch-normalised."""
    grey = np.asarray(Image.open(path).convert("L"), np.float32)  # 32 x 64
    small = grey.reshape(16, 2, 32, 2).mean(axis=(1, 3))
    patches = small.reshape(4, 4, 8, 4).transpose(0, 2, 1, 3).reshape(32, 16)
    patches = (patches - patches.mean(axis=1, keepdims=True)) / (patches.std(axis=1, keepdims=True) + 1e-3)
    return patches.reshape(-1)


class LinearEncoder:
    """The user's model: code = normalise(x W); W 512 x 64, seeded."""

    def __init__(self, dim_in: int, dim_out: int, seed: int):
        self.w = np.random.default_rng(seed).standard_normal((dim_in, dim_out)).astype(np.float32)
        self.w /= np.sqrt(dim_in)

    def encode(self, x: np.ndarray) -> np.ndarray:
        y = x @ self.w
        return y / np.linalg.norm(y, axis=1, keepdims=True)

    def train_triplets(self, x, places, domains, steps: int, seed: int, lr=0.05, margin=0.5, batch=64):
        """Triplet loss on cosine distance: anchor and positive are the same
        place (within TOLERANCE) in different seasons, the negative a place
        at least 50 frames away. Plain SGD with hand-written gradients."""
        rng = np.random.default_rng(seed)
        same = (np.abs(places[:, None] - places[None, :]) <= TOLERANCE) & (domains[:, None] != domains[None, :])
        anchors = np.flatnonzero(same.any(axis=1))
        losses = []
        if len(anchors) == 0:  # the replay holds no place seen in both seasons
            return losses
        for _ in range(steps):
            a = rng.choice(anchors, batch)
            p = np.array([rng.choice(np.flatnonzero(same[i])) for i in a])
            n = rng.integers(0, len(x), batch)
            far = np.abs(places[n] - places[a]) > 50 * 10
            a, p, n = a[far], p[far], n[far]
            ya, yp, yn = x[a] @ self.w, x[p] @ self.w, x[n] @ self.w
            norms = [np.linalg.norm(y, axis=1, keepdims=True) for y in (ya, yp, yn)]
            za, zp, zn = ya / norms[0], yp / norms[1], yn / norms[2]
            loss = margin - 2 * np.sum(za * zp, 1) + 2 * np.sum(za * zn, 1)
            active = (loss > 0)[:, None]
            losses.append(float(np.maximum(loss, 0).mean()))
            grads = (active * (2 * zn - 2 * zp), active * (-2 * za), active * (2 * za))
            dw = np.zeros_like(self.w)
            for xi, z, norm, g in zip((x[a], x[p], x[n]), (za, zp, zn), norms, grads):
                dy = (g - z * np.sum(g * z, 1, keepdims=True)) / norm  # through the normalisation
                dw += xi.T @ dy
            self.w -= lr * dw / max(1, len(a))
        return losses


def recall_at_1(fm, fleet, codes, places):
    hits = 0
    for code, place in zip(codes, places):
        match = fm.query_place(fleet, code, k=1)
        hits += len(match) == 1 and abs(match.traces.places[0, 0] - place) <= TOLERANCE
    return hits / len(codes)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--server", default="127.0.0.1:50051")
    parser.add_argument("--data-root", default="../shared/data")
    parser.add_argument("--fleet", default=None,
                        help="fleets NAME-v1 and NAME-v2 (default: nordland-py-<unix time>, new each run)")
    parser.add_argument("--replace", action="store_true",
                        help="delete NAME-v1 and NAME-v2 first if they exist (else the run stops)")
    parser.add_argument("--stride", type=int, default=5, help="use every STRIDE-th frame (default 5: 500 places)")
    parser.add_argument("--replay", type=int, default=600, help="traces sampled for training")
    parser.add_argument("--steps", type=int, default=300, help="training steps, over all batches")
    parser.add_argument("--epochs", type=int, default=3, help="replay batches of --replay traces")
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()

    root = pathlib.Path(args.data_root) / "nordland"
    names = sorted(p.name for p in (root / "summer").glob("images-*.png"))[::args.stride]
    places = np.array([int(n[len("images-"):-len(".png")]) for n in names], np.float64)
    started = time.monotonic()
    x = {season: np.stack([descriptor(root / season / n) for n in names]) for season in ("summer", "winter")}
    half = len(names) // 2
    print(f"{len(names)} places per season, descriptors in {time.monotonic() - started:.1f} s; "
          f"winter uploads places {places[0]:.0f}..{places[half - 1]:.0f}, "
          f"queries {places[half]:.0f}..{places[-1]:.0f} are held out")

    model = LinearEncoder(x["summer"].shape[1], 64, args.seed)
    name = args.fleet or f"nordland-py-{int(time.time())}"
    v1, v2 = f"{name}-v1", f"{name}-v2"
    with fleetmem.Client(args.server) as fm:
        # Uploads into a fleet that holds these seqs already store nothing
        # (duplicates), and the recall below would measure the old codes.
        held = {f.fleet_id for f in fm.fleets()} & {v1, v2}
        if held and not args.replace:
            parser.error(f"fleet(s) {', '.join(sorted(held))} exist already: a second run into them "
                         f"would upload only duplicates and measure the first run's codes; give another "
                         f"--fleet, or --replace to delete them first")
        for fleet in sorted(held):
            print(f"deleted fleet {fleet} ({fm.delete_fleet(fleet)} traces)")
        print(f"fleets {v1} and {v2}")

        def upload(fleet, season, rows, version, robot):
            codes = model.encode(x[season][rows])
            # Reward: novelty against the previous frame (R_in, Eq. 13's spirit).
            novelty = np.concatenate([[1.0], 1.0 - np.sum(codes[1:] * codes[:-1], 1)]).clip(0.01, 2)
            result = fm.upload(fleet, codes, places[rows], novelty, robot_id=robot, seqs=np.asarray(rows),
                               domain=season, encoder_version=version,
                               attachments=x[season][rows].astype("<f4"))
            if result.duplicates:
                sys.exit(f"{fleet}: {result.duplicates} of robot {robot}'s traces were held already: stopped")
            return result
        all_rows, first_half = np.arange(len(names)), np.arange(half)
        print("summer robot:", upload(v1, "summer", all_rows, "linear-v1", "summer"))
        print("winter robot:", upload(v1, "winter", first_half, "linear-v1", "winter"))
        fm.consolidate(v1)  # every robot's pending traces into the static memory the replay draws
        held_out = np.arange(half, len(names))
        before = recall_at_1(fm, v1, model.encode(x["winter"][held_out]), places[held_out])
        print(f"recall@1 of {len(held_out)} held-out winter frames, model v1: {before:.3f}")

        # Replay as a stream of batches (fleetmem.ReplayDataset): each batch
        # one draw of the fleet's memory (weight gamma^n R, so each draw
        # favours traces replayed less), the next drawn while this one trains.
        dataset = fleetmem.ReplayDataset(fm, v1, "winter", batch_size=args.replay, batches=args.epochs)
        started = time.monotonic()
        losses = []
        for epoch, replay in enumerate(dataset):
            if len(replay) == 0:
                print("the fleet's static memory is empty: nothing to replay")
                break
            features = np.stack([np.frombuffer(a, "<f4") for a in replay.attachments])
            domains = np.array(replay.domains)
            print(f"replay batch {epoch + 1}: {len(replay)} traces ({np.sum(domains == 'summer')} summer, "
                  f"{np.sum(domains == 'winter')} winter), mean reward {replay.rewards.mean():.3f}")
            losses += model.train_triplets(features, replay.places[:, 0], domains,
                                           max(1, args.steps // args.epochs), args.seed + epoch)
        if not losses:
            print("the replay holds no place seen in both seasons: nothing to train on")
        else:
            print(f"trained {args.steps} steps in {time.monotonic() - started:.1f} s: "
                  f"triplet loss {np.mean(losses[:20]):.3f} -> {np.mean(losses[-20:]):.3f}")

        # A new encoder version is a new fleet: everything the old one holds
        # is re-encoded from its attachment (other robots' traces too).
        old = fm.export(v1)
        for robot in sorted(set(old.robot_ids)):
            rows = np.flatnonzero(np.array(old.robot_ids) == robot)
            raw = np.stack([np.frombuffer(old.attachments[i], "<f4") for i in rows])
            fm.upload(v2, model.encode(raw), old.places[rows], old.rewards[rows], robot_id=robot,
                      seqs=old.seqs[rows], domain=old.domains[rows[0]], encoder_version="linear-v2",
                      attachments=raw)
        after = recall_at_1(fm, v2, model.encode(x["winter"][held_out]), places[held_out])
        print(f"recall@1 of {len(held_out)} held-out winter frames, model v2: {after:.3f} (v1: {before:.3f})")


if __name__ == "__main__":
    main()
