"""Are the episodes in a folder the ones a policy was trained and validated on?

Calibration must score the validation episodes the policy held out, and a fine-tuning job must mix in
the training episodes it was trained on. Both find them by name in a folder, and the names carry the
task and the seed; what they do not carry is how the episode was recorded. Two kinds of evidence
identify one:

- **Its content.** ``hitl train`` records a digest of every validation episode's steps
  (``episode_digest``: the float32 observations and actions, nothing else), so an episode that is
  the same data is recognised whatever its file looks like. File sizes are no such evidence: a
  recording's timestamps start at the wall clock and its chunks are compressed, so the same steps,
  recorded twice, give files of different sizes. Older policies recorded sizes
  (``val_episode_bytes``); they are not read.
- **Its provenance, where the content differs.** A folder that a fine-tuning job records again from
  the policy's recipe (``sim.demos.DemoRecipe``) on another machine is the same scripted expert on
  the same seeds with the same execution noise, but not always bit for bit the same data where the
  machine, the simulator's build or the project's code differ (an episode the expert succeeded in
  where the policy was trained may time out, recorded again). An episode whose own metadata says it
  was recorded that way (task, seed, expert source, execution noise) counts as the held-out episode,
  recorded again, and the record says how many were identified that way (``by_recipe``).

Anything else (a folder recorded without the noise, or by a different task or seed under the same
names) is refused.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from sim.demos import DemoRecipe
from storage import keys
from storage.dataset import DemoDataset

DIGEST = "sha256"


def episode_digest(ds: DemoDataset, e: int) -> str:
    """``sha256:<hex>`` of episode ``e``'s observations and actions (float32, row order)."""
    s, t = int(ds.episode_starts[e]), int(ds.episode_ends[e])
    h = hashlib.sha256()
    for part in (ds.obs[s:t], ds.actions[s:t]):
        h.update(np.ascontiguousarray(part, dtype=np.float32).tobytes())
    return f"{DIGEST}:{h.hexdigest()}"


def recorded_by(meta: dict, recipe: DemoRecipe) -> bool:
    """Whether an episode's metadata says ``recipe`` recorded it: the recipe's task, one of its seeds,
    the scripted expert, and the recipe's execution noise (none when the recipe has none)."""
    seed = meta.get("seed")
    if meta.get("task") != recipe.task or meta.get("source") != keys.SOURCE_EXPERT:
        return False
    if not (isinstance(seed, int) and recipe.seed <= seed < recipe.seed + recipe.episodes):
        return False
    noise = meta.get("execution_noise") or {"pos": 0.0, "rot": 0.0}
    return bool(
        np.isclose(noise.get("pos", 0.0), recipe.pos_noise) and np.isclose(noise.get("rot", 0.0), recipe.rot_noise)
    )


class HeldOutError(ValueError):
    """The folder's episodes are not the ones the policy held out; the message says which and why."""


@dataclass(frozen=True)
class HeldOutCheck:
    """identical: episodes whose digest matches the policy's record; by_recipe: episodes with no digest
    to match (training episodes, or content that differs, as in a folder recorded again elsewhere) whose
    metadata says the policy's recipe recorded them; unverified: episodes of a policy that recorded
    neither digests nor a recipe (trusted by name, as before digests)."""

    identical: int = 0
    by_recipe: int = 0
    unverified: int = 0

    def to_dict(self) -> dict:
        return {"identical": self.identical, "by_recipe": self.by_recipe, "unverified": self.unverified}


def check_held_out(ds: DemoDataset, episodes: list[int], info: dict) -> HeldOutCheck:
    """Checks ``ds``'s episodes ``episodes`` (indices) against the policy's config.json ``info``: by digest
    where it recorded one, else by the recipe's provenance. Raises ``HeldOutError`` for an episode that
    is neither."""
    split = info.get("dataset", {}) or {}
    digests = split.get("val_episode_digest") or {}
    recipe = DemoRecipe.from_dict(split["recipe"]) if split.get("recipe") else None
    identical = by_recipe = unverified = 0
    refused: list[str] = []
    for e in episodes:
        name, meta = ds.names[e], ds.meta[e]
        if name in digests and episode_digest(ds, e) == digests[name]:
            identical += 1
        elif recipe is not None and recorded_by(meta, recipe):
            by_recipe += 1
        elif name not in digests and recipe is None:
            unverified += 1
        else:
            refused.append(name)
    if refused:
        why = (
            "its steps differ from the ones the policy held out"
            if recipe is None
            else "its steps differ, and its metadata does not say that the policy's recipe "
            f"({recipe.command('…')}) recorded it"
        )
        raise HeldOutError(
            f"{len(refused)} episode(s) in {ds.folder} are not the ones the policy was trained and validated on "
            f"(e.g. {refused[0]}: {why}): is this the folder the policy was trained from?"
        )
    return HeldOutCheck(identical, by_recipe, unverified)
