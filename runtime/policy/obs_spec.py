"""The observation contract: which features the actor sees, in which order, how normalised, and
how its action maps back to a twist. Defined once here; training, export and the robot use it.

An `ObsSpec` is an ordered list of feature blocks plus the action mapping, versioned and stored
as JSON (in the ONNX file's metadata by `safemove export`). Every feature is a float32 in a
fixed range (`ObsSpec.bounds()`), so a policy never sees raw metres. The builder clips every
feature into its range (the training observation space and the export's parity sampling are that
box); a NaN input stays NaN, so the runtime's non-finite check still sees it and brakes:

| block      | features (in this order)                                  | range     |
|------------|-----------------------------------------------------------|-----------|
| `goal`     | min(distance / distance_max_m, 1), sin(bearing), cos(bearing) | [0,1], [-1,1] |
| `velocity` | v, ω of odometry, normalised like an action (see below)    | [-1, 1]   |
| `scan`     | `bins` free ranges over `span_deg`, right to left: min(r, range_max_m) / range_max_m; a bin with no obstacle return is 1; a bin that is unknown, or that the camera does not cover, is 0 (near/occupied, never free) | [0, 1] |
| `dwa`      | DWA's best (v, ω) normalised like an action; `path_points` (x, y) of its path in base_link / path_scale_m (points at equal time steps, the last at the horizon); its heading, clearance, velocity, density terms (each divided by DWA's scale σ, clipped to [0, 1]) | [-1,1], [-1,1], [0,1] |
| `corridor` | left free widths of the `samples` corridor samples / width_max_m, then the right ones | [0, 1] |

Goal bearing and all positions are in base_link (x forward, y left). Velocities are normalised
with the action mapping's own box: v ↦ 2(v − v_min)/(v_max − v_min) − 1, ω ↦ ω/ω_max, clipped,
so a feature and an action that mean the same speed have the same value.

Where a value can leave its range, the clip decides: the DWA density term is unbounded above
(its scale σ, density_scale, is the density that counts as 1, e.g. two obstacles at an average
0.5 m; more or nearer obstacles exceed it), so it reads 1 from σ up; a reversing sample's
velocity term (v / σ < 0, only where the limits allow v < 0) reads 0; a negative range reads 0;
and range_max_m · (1 / range_max_m) rounding above 1 in float32 (e.g. range_max_m = 1.7) reads 1.

Action mapping: the model outputs a ∈ [output_low, output_high]² (default [−1, 1]²; a
stable-baselines3 export outputs its action space's box), clipped to it, then mapped linearly
onto v ∈ [v_min, v_max], ω ∈ [−ω_max, ω_max].

Presets: the paper's ablation variants, `drl` (goal, velocity, scan), `drl_dwa` (+ dwa) and
`safemove` (+ corridor).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from runtime.config.schema import build, setting, to_plain
from runtime.errors import ConfigError
from runtime.types import Twist

SPEC_VERSION = 1
F32 = np.float32


class SpecError(ConfigError):
    """An observation spec that cannot be used (one line naming its source and key)."""


# --- blocks --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GoalBlock:
    kind: ClassVar[str] = "goal"
    distance_max_m: float = setting(10.0, "goal distance saturates at this", "m",
                                    min=0.1, max=1000.0)

    @property
    def size(self) -> int:
        return 3

    def names(self) -> list[str]:
        return ["goal.distance", "goal.sin_bearing", "goal.cos_bearing"]

    def bounds(self) -> tuple[list[float], list[float]]:
        return [0.0, -1.0, -1.0], [1.0, 1.0, 1.0]


@dataclass(frozen=True)
class VelocityBlock:
    kind: ClassVar[str] = "velocity"

    @property
    def size(self) -> int:
        return 2

    def names(self) -> list[str]:
        return ["velocity.v", "velocity.omega"]

    def bounds(self) -> tuple[list[float], list[float]]:
        return [-1.0, -1.0], [1.0, 1.0]


@dataclass(frozen=True)
class ScanBlock:
    kind: ClassVar[str] = "scan"
    bins: int = setting(20, "bearing bins, right to left", min=1, max=1024)
    span_deg: float = setting(87.0, "bearing span of the bins, centred ahead", "deg",
                              min=1.0, max=360.0)
    range_max_m: float = setting(4.0, "ranges saturate at this (no return: this)", "m",
                                 min=0.1, max=100.0)

    @property
    def size(self) -> int:
        return self.bins

    def names(self) -> list[str]:
        return [f"scan[{i}]" for i in range(self.bins)]

    def bounds(self) -> tuple[list[float], list[float]]:
        return [0.0] * self.bins, [1.0] * self.bins


@dataclass(frozen=True)
class DWABlock:
    kind: ClassVar[str] = "dwa"
    path_points: int = setting(5, "points taken from the best path at equal time steps",
                               min=1, max=200)
    path_scale_m: float = setting(0.9, "path coordinates are divided by this (the distance"
                                  " v_max covers in the DWA horizon)", "m", min=0.01, max=100.0)

    @property
    def size(self) -> int:
        return 2 + 2 * self.path_points + 4

    def names(self) -> list[str]:
        path = [f"dwa.path[{i}].{c}" for i in range(self.path_points) for c in ("x", "y")]
        return ["dwa.best_v", "dwa.best_omega", *path, "dwa.heading", "dwa.clearance",
                "dwa.velocity", "dwa.density"]

    def bounds(self) -> tuple[list[float], list[float]]:
        n = 2 + 2 * self.path_points
        return [-1.0] * n + [0.0] * 4, [1.0] * (n + 4)


@dataclass(frozen=True)
class CorridorBlock:
    kind: ClassVar[str] = "corridor"
    samples: int = setting(10, "corridor samples K along the best path", min=1, max=1000)
    width_max_m: float = setting(1.5, "free widths saturate at this (the corridor's cap)", "m",
                                 min=0.01, max=20.0)

    @property
    def size(self) -> int:
        return 2 * self.samples

    def names(self) -> list[str]:
        return ([f"corridor.left[{i}]" for i in range(self.samples)]
                + [f"corridor.right[{i}]" for i in range(self.samples)])

    def bounds(self) -> tuple[list[float], list[float]]:
        return [0.0] * self.size, [1.0] * self.size


Block = GoalBlock | VelocityBlock | ScanBlock | DWABlock | CorridorBlock
BLOCK_TYPES: dict[str, type] = {
    b.kind: b for b in (GoalBlock, VelocityBlock, ScanBlock, DWABlock, CorridorBlock)
}


@dataclass(frozen=True)
class ActionSpec:
    v_min: float = setting(0.0, "a at output_low[0] maps to this speed (the camera sees only"
                           " ahead, so the presets never reverse)", "m/s", min=-5.0, max=5.0)
    v_max: float = setting(0.3, "a at output_high[0] maps to this speed", "m/s",
                           min=-5.0, max=5.0)
    omega_max: float = setting(1.0, "a[1] at output_low/high maps to ∓/± this", "rad/s",
                               min=0.0, max=20.0, min_exclusive=True)
    output_low: tuple[float, float] = setting((-1.0, -1.0), "the model's output box, low end")
    output_high: tuple[float, float] = setting((1.0, 1.0), "the model's output box, high end")

    def to_twist(self, a: np.ndarray) -> Twist:
        """Model output (2,) → twist; the output is clipped to its box first."""
        lo, hi = self.output_low, self.output_high
        u0 = (min(max(float(a[0]), lo[0]), hi[0]) - lo[0]) / (hi[0] - lo[0])
        u1 = (min(max(float(a[1]), lo[1]), hi[1]) - lo[1]) / (hi[1] - lo[1])
        return Twist(self.v_min + u0 * (self.v_max - self.v_min),
                     (2.0 * u1 - 1.0) * self.omega_max)

    def normalise(self, v: float, omega: float) -> tuple[float, float]:
        """A twist in the [-1, 1]² action space (clipped): how velocity features are scaled."""
        vn = 2.0 * (v - self.v_min) / (self.v_max - self.v_min) - 1.0
        return min(max(vn, -1.0), 1.0), min(max(omega / self.omega_max, -1.0), 1.0)


# --- the spec ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ObsSpec:
    name: str
    blocks: tuple[Block, ...]
    action: ActionSpec = ActionSpec()
    version: int = SPEC_VERSION

    @property
    def size(self) -> int:
        return sum(b.size for b in self.blocks)

    def block(self, kind: str) -> Any:
        """The block of that kind, or None."""
        return next((b for b in self.blocks if b.kind == kind), None)

    def layout(self) -> list[tuple[str, int, int]]:
        """(kind, start, stop) of each block in the vector."""
        out, start = [], 0
        for b in self.blocks:
            out.append((b.kind, start, start + b.size))
            start += b.size
        return out

    def names(self) -> list[str]:
        return [n for b in self.blocks for n in b.names()]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-feature (low, high): every observation this spec builds lies inside."""
        lo = [x for b in self.blocks for x in b.bounds()[0]]
        hi = [x for b in self.blocks for x in b.bounds()[1]]
        return np.array(lo, dtype=F32), np.array(hi, dtype=F32)

    def to_dict(self) -> dict[str, Any]:
        return {
            "spec_version": self.version,
            "name": self.name,
            "blocks": [{"type": b.kind, **to_plain(b)} for b in self.blocks],
            "action": to_plain(self.action),
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), separators=(",", ":"))

    @classmethod
    def from_dict(cls, data: Any, source: str) -> ObsSpec:
        """Validate parsed JSON; errors name the source and the key ("blocks[2].bins")."""
        if not isinstance(data, dict):
            raise SpecError(f"{source}: an observation spec must be a JSON object")
        known = {"spec_version", "name", "blocks", "action"}
        for key in data:
            if key not in known:
                raise SpecError(f"{source}: unknown key '{key}' (known: {', '.join(sorted(known))})")
        version = data.get("spec_version")
        if isinstance(version, bool) or not isinstance(version, int):
            raise SpecError(f"{source}: key 'spec_version': expected an integer, got {version!r}")
        if version > SPEC_VERSION or version < 1:
            raise SpecError(f"{source}: key 'spec_version': this runtime reads version"
                            f" {SPEC_VERSION}, got {version}")
        name = data.get("name", "custom")
        if not isinstance(name, str) or not name:
            raise SpecError(f"{source}: key 'name': expected a non-empty string, got {name!r}")
        raw_blocks = data.get("blocks")
        if not isinstance(raw_blocks, list) or not raw_blocks:
            raise SpecError(f"{source}: key 'blocks': expected a non-empty list of blocks")
        blocks: list[Block] = []
        for i, raw in enumerate(raw_blocks):
            where = f"blocks[{i}]"
            if not isinstance(raw, dict):
                raise SpecError(f"{source}: key '{where}': expected an object with a 'type'")
            kind = raw.get("type")
            if kind not in BLOCK_TYPES:
                raise SpecError(f"{source}: key '{where}.type': must be one of"
                                f" {', '.join(BLOCK_TYPES)}, got {kind!r}")
            if any(b.kind == kind for b in blocks):
                raise SpecError(f"{source}: key '{where}.type': block '{kind}' appears twice")
            params = {k: v for k, v in raw.items() if k != "type"}
            blocks.append(_build(BLOCK_TYPES[kind], params, source, f"{where}."))
        action = _build(ActionSpec, data.get("action", {}), source, "action.")
        if not action.v_max > action.v_min:
            raise SpecError(f"{source}: key 'action.v_max': must be greater than action.v_min"
                            f" ({action.v_min}), got {action.v_max}")
        for k in range(2):
            if not action.output_high[k] > action.output_low[k]:
                raise SpecError(f"{source}: key 'action.output_high': each must be greater than"
                                f" output_low, got {list(action.output_low)} →"
                                f" {list(action.output_high)}")
        return cls(name, tuple(blocks), action, version)

    @classmethod
    def from_json(cls, text: str, source: str) -> ObsSpec:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise SpecError(f"{source}: not valid JSON: {exc.msg} (line {exc.lineno})") from None
        return cls.from_dict(data, source)


def _build(cls: type, data: Any, source: str, prefix: str) -> Any:
    try:
        return build(cls, data, source, prefix)
    except ConfigError as exc:
        raise SpecError(str(exc)) from None


PRESETS: dict[str, ObsSpec] = {
    "drl": ObsSpec("drl", (GoalBlock(), VelocityBlock(), ScanBlock())),
    "drl_dwa": ObsSpec("drl_dwa", (GoalBlock(), VelocityBlock(), ScanBlock(), DWABlock())),
    "safemove": ObsSpec("safemove", (GoalBlock(), VelocityBlock(), ScanBlock(), DWABlock(),
                                     CorridorBlock())),
}


def load_spec(name_or_path: str) -> ObsSpec:
    """A preset by name, or a spec JSON file."""
    if name_or_path in PRESETS:
        return PRESETS[name_or_path]
    path = Path(name_or_path)
    if path.suffix.lower() != ".json" and not path.exists():
        raise SpecError(f"--spec {name_or_path}: not a preset ({', '.join(PRESETS)}) nor a"
                        " spec .json file")
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SpecError(f"{path}: spec file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SpecError(f"{path}: cannot read the spec file: {exc}") from None
    return ObsSpec.from_json(text, str(path))


def with_action_box(spec: ObsSpec, low: tuple[float, float], high: tuple[float, float]) -> ObsSpec:
    """The same spec for a model whose output box is [low, high] (e.g. an SB3 action space)."""
    return replace(spec, action=replace(spec.action, output_low=low, output_high=high))


# --- building observations -----------------------------------------------------------------------


class ObservationBuilder:
    """Builds a spec's observations into one preallocated float32 vector (reused every call).

    Inputs: the goal in base_link, odometry's (v, ω), and, where the spec's blocks need them,
    the world (anything with `scan`, `unknown`, `bin_angles`: runtime.process.loop.WorldState), the DWA
    result (runtime.planning.dwa.DWAResult) and the corridor (runtime.planning.corridor.Corridor).
    Every feature of the result lies in `spec.bounds()` or is NaN (a NaN input stays NaN).
    """

    def __init__(self, spec: ObsSpec) -> None:
        self.spec = spec
        self.vector = np.zeros(spec.size, dtype=F32)
        self._lo, self._hi = spec.bounds()
        self._slices = {kind: slice(a, b) for kind, a, b in spec.layout()}
        self._scan_angles: np.ndarray | None = None
        self._scan_mask: np.ndarray | None = None  # (spec bins, perception bins) overlap
        self._scan_tmp: np.ndarray | None = None

    def build(self, goal_base: np.ndarray, v: float, omega: float, world: Any = None,
              dwa: Any = None, corridor: Any = None) -> np.ndarray:
        """The observation (the builder's own vector: copy it to keep it)."""
        out = self.vector
        act = self.spec.action
        for block in self.spec.blocks:
            o = out[self._slices[block.kind]]
            if isinstance(block, GoalBlock):
                gx, gy = float(goal_base[0]), float(goal_base[1])
                b = math.atan2(gy, gx)
                o[:] = (min(math.hypot(gx, gy) / block.distance_max_m, 1.0), math.sin(b),
                        math.cos(b))
            elif isinstance(block, VelocityBlock):
                o[:] = act.normalise(v, omega)
            elif isinstance(block, ScanBlock):
                if world is None:
                    raise ValueError("the scan block needs the world state")
                self._scan(block, world, o)
            elif isinstance(block, DWABlock):
                if dwa is None:
                    raise ValueError("the dwa block needs the DWA result")
                self._dwa(block, dwa, o)
            else:
                if corridor is None:
                    raise ValueError("the corridor block needs the corridor")
                k = block.samples
                if len(corridor.left) != k:
                    raise ValueError(f"the spec's corridor has {k} samples, the corridor"
                                     f" {len(corridor.left)}")
                np.clip(np.asarray(corridor.left) / block.width_max_m, 0.0, 1.0, out=o[:k])
                np.clip(np.asarray(corridor.right) / block.width_max_m, 0.0, 1.0, out=o[k:])
        # the contract, in place (no temporaries): np.clip keeps NaN
        np.clip(out, self._lo, self._hi, out=out)
        return out

    def _dwa(self, block: DWABlock, dwa: Any, o: np.ndarray) -> None:
        o[0:2] = self.spec.action.normalise(*dwa.best)
        path = dwa.best_path
        steps, k = len(path), block.path_points
        if k > steps:
            raise ValueError(f"the spec wants {k} path points, the DWA path has {steps} steps")
        rows = (np.arange(1, k + 1) * steps) // k - 1
        np.clip(path[rows, :2].reshape(-1) / block.path_scale_m, -1.0, 1.0, out=o[2:2 + 2 * k])
        i = dwa.best_index
        # the terms over their scale σ; build() clips them to [0, 1] (density exceeds σ)
        o[2 + 2 * k:] = (dwa.heading[i], dwa.clearance[i], dwa.velocity[i], dwa.density[i])

    def _scan(self, block: ScanBlock, world: Any, o: np.ndarray) -> None:
        angles = world.bin_angles
        if self._scan_angles is None or not np.array_equal(self._scan_angles, angles):
            self._scan_mask = _scan_overlap(block, np.asarray(angles, dtype=float))
            self._scan_angles = np.array(angles, copy=True)
            self._scan_tmp = np.empty(self._scan_mask.shape, dtype=F32)
        mask, tmp = self._scan_mask, self._scan_tmp
        assert mask is not None and tmp is not None
        # per perception bin: free range in [0, range_max]; unknown (or NaN) → 0 (occupied)
        r = np.minimum(np.asarray(world.scan, dtype=F32), F32(block.range_max_m))
        r[np.asarray(world.unknown, dtype=bool) | np.isnan(r)] = 0.0
        np.copyto(tmp, r[None, :])
        tmp[~mask] = np.inf
        np.min(tmp, axis=1, out=o)
        o[np.isinf(o)] = 0.0  # a spec bin the camera does not cover is unseen, never free
        o *= F32(1.0 / block.range_max_m)  # build() clips to [0, 1]: r < 0, float32 rounding


def _scan_overlap(block: ScanBlock, angles: np.ndarray) -> np.ndarray:
    """(spec bins, perception bins): which perception bins' wedges overlap each spec bin's."""
    half = math.radians(block.span_deg) / 2.0
    edges = np.linspace(-half, half, block.bins + 1)
    width = float(np.median(np.diff(angles))) if len(angles) > 1 else 2.0 * half
    p_lo, p_hi = angles - width / 2.0, angles + width / 2.0
    lo = np.maximum(edges[:-1, None], p_lo[None, :])
    hi = np.minimum(edges[1:, None], p_hi[None, :])
    return hi > lo + 1e-3 * width  # not a float-rounding sliver of a neighbour

