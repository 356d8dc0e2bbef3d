"""Settings checks shared by the recipes' structured configs (one home for them).

A recipe's settings are frozen dataclasses (the schema and the defaults), registered as a Hydra
structured config so that every key can be overridden without ``+`` and OmegaConf rejects
unknown keys and values of the wrong type. The dataclasses check ranges in ``__post_init__``
with the helpers below; :func:`build_config` then turns a composed config into the typed one,
and :func:`check_run_settings` checks what depends on the machine (the device, the run
directory) before anything is created or written. Every error is a ``ValueError`` naming the
setting, what was expected and what was given.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import tempfile
import typing
from collections.abc import Callable, Sequence
from pathlib import Path
from types import UnionType
from typing import Any, TypeVar

import torch
from omegaconf import DictConfig, OmegaConf

from rcvae_torchrl import threads as threads_module

__all__ = [
    "RUN_MADE",
    "run_dir_refusal",
    "CHECKPOINTS",
    "SEED_MAX",
    "at_least",
    "build_config",
    "check_command_line",
    "claim_run_dir",
    "say_checks",
    "typed_settings",
    "check_device_name",
    "check_override_keys",
    "check_printed_config",
    "check_profile",
    "check_run_dir",
    "check_run_dir_name",
    "check_reuse_from",
    "check_run_settings",
    "check_seed",
    "check_sequences",
    "check_threads",
    "register_schema",
    "resolve_device",
    "set_threads",
    "whole_steps",
]

SEED_MAX = 2**32 - 1  #: the largest seed every generator of a run accepts (numpy's limit)

T = TypeVar("T")


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def at_least(name: str, value: Any, low: float, kind: type = float) -> None:
    """Require a finite number (an ``int`` when ``kind`` is ``int``) >= ``low``."""
    ok = _is_number(value) and math.isfinite(value) and value >= low
    if kind is int:
        ok = ok and isinstance(value, int)
    if not ok:
        what = "an integer" if kind is int else "a finite number"
        raise ValueError(f"{name}: expected {what} >= {low}, got {value!r}")


def whole_steps(name: str, seconds: Any, step: float) -> int:
    """The number of ``step``-second control steps in ``seconds`` (a positive whole number)."""
    steps = seconds / step if _is_number(seconds) else math.nan
    if not (math.isfinite(steps) and steps >= 1 and abs(steps - round(steps)) < 1e-6):
        raise ValueError(
            f"{name}: expected a positive whole number of {step} s control steps, got {seconds!r}"
        )
    return round(steps)


def check_field_types(config: Any, prefix: str = "") -> None:
    """Require each field of the dataclass ``config`` that holds a section (a dataclass) to be
    one, and each ``bool`` field a bool: built in Python rather than by Hydra (which types
    them), a dict for a section would skip the section's own checks, and ``"no"`` for a flag
    would read as True."""
    hints = typing.get_type_hints(type(config))
    for field in dataclasses.fields(config):
        value, hint = getattr(config, field.name), hints.get(field.name)
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            if not isinstance(value, hint):
                raise TypeError(
                    f"{prefix}{field.name}: expected {hint.__name__} settings (the section), "
                    f"got {type(value).__name__}"
                )
            check_field_types(value, f"{prefix}{field.name}.")
        elif hint is bool and not isinstance(value, bool):
            raise TypeError(f"{prefix}{field.name}: expected true or false, got {value!r}")


def check_sequences(config: Any) -> None:
    """Require each field of the dataclass ``config`` typed as a tuple or a list to hold a list
    or a tuple (``None`` where the type allows it): built in Python rather than by Hydra (which
    types them), a scalar such as ``exploration_std=0.3`` would otherwise fail in the section's
    own checks as "'float' object is not iterable". Call it first in a section's
    ``__post_init__``."""
    hints = typing.get_type_hints(type(config))
    for field in dataclasses.fields(config):
        hint = hints.get(field.name)
        options = (
            typing.get_args(hint)
            if typing.get_origin(hint) in (typing.Union, UnionType)
            else (hint,)
        )
        kinds = [typing.get_origin(option) or option for option in options]
        if not any(kind in (tuple, list) for kind in kinds):
            continue
        value = getattr(config, field.name)
        if value is None and type(None) in kinds:
            continue
        if not isinstance(value, (list, tuple)):
            raise ValueError(
                f"{field.name}: expected a list of values"
                + (" or null" if type(None) in kinds else "")
                + f", got {value!r}"
            )


def check_profile(value: Any, profiles: Path) -> None:
    """Require the name of a profile in the folder ``profiles`` (a recipe's
    ``conf/profile``, one ``<name>.yaml`` per profile)."""
    names = sorted(path.stem for path in Path(profiles).glob("*.yaml"))
    if value not in names:
        raise ValueError(f"profile: expected one of {names} ({profiles}), got {value!r}")


def check_seed(name: str, value: Any, maximum: int = SEED_MAX) -> None:
    """Require an integer seed in ``[0, maximum]`` (default ``2**32 - 1``; a study whose real
    episodes' seeds grow with it, ``seed·100_003`` each in ``real_outcomes``, allows less)."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= maximum:
        if maximum == SEED_MAX:
            raise ValueError(f"{name}: expected an integer in [0, 2**32 - 1], got {value!r}")
        raise ValueError(
            f"{name}: expected an integer in [0, {maximum}] (the study's real episodes are "
            f"seeded from it, and an env's seed stays below 2**32), got {value!r}"
        )


def check_threads(value: Any) -> None:
    """Require ``"auto"``, ``None`` (torch's default) or an integer >= 1."""
    if value in (None, "auto"):
        return
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"threads: expected a positive integer, 'auto' or null, got {value!r}")


def check_device_name(name: Any) -> None:
    """Require ``"auto"``, ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` (whether present: see
    :func:`resolve_device`)."""
    if not isinstance(name, str) or not re.fullmatch(r"auto|cpu|cuda(:\d+)?", name):
        raise ValueError(f"device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got {name!r}")


def resolve_device(name: Any) -> str:
    """The device a run uses: ``"auto"`` -> ``"cuda"`` when present, else ``"cpu"``.

    ``"cpu"``, ``"cuda"`` and ``"cuda:N"`` are accepted only when present on this machine;
    anything else (``"tpu"``, ``"meta"``, a bare number) is a ``ValueError`` naming ``device``.
    """
    check_device_name(name)
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ValueError(f"device: {name!r} asked for, but CUDA is not available here")
        count = torch.cuda.device_count()
        index = int(name.partition(":")[2] or 0)
        if index >= count:
            raise ValueError(
                f"device: {name!r} asked for, but this machine has {count} CUDA device(s) "
                f"(cuda:0 to cuda:{count - 1})"
            )
    return name


def check_run_dir_name(value: Any) -> None:
    """Require a non-empty path (whether writable: see :func:`check_run_dir`)."""
    if not isinstance(value, str) or not value.strip():
        raise ValueError(f"run_dir: expected a directory path, got {value!r}")


def check_run_dir(value: Any) -> Path:
    """Require a non-empty directory path that exists and is writable or can be created.

    Nothing is left behind: a directory is made and removed in the nearest existing ancestor.
    """
    check_run_dir_name(value)
    path = Path(value).expanduser().absolute()
    if path.exists() and not path.is_dir():
        raise ValueError(f"run_dir: expected a directory, got {value!r} (an existing file)")
    existing = path
    while not existing.exists():
        existing = existing.parent
    try:  # the one sure test (permissions, read-only mounts, /proc): make a directory there
        os.rmdir(tempfile.mkdtemp(prefix=".run_dir_check.", dir=existing))
    except OSError as err:
        where = "it" if existing == path else f"its parent {str(existing)!r}"
        raise ValueError(
            f"run_dir: expected a writable directory, got {value!r} (no directory can be "
            f"created in {where}: {err.strerror})"
        ) from None
    return path


def set_threads(threads: int | str | None, op_flop: float | None = None) -> int:
    """Set torch's intra-op threads: a count, ``"auto"`` (one thread unless the machine has idle
    cores and the recipe's typical op of ``op_flop`` FLOP is large, see
    :func:`rcvae_torchrl.threads.choose_threads`) or ``None`` (torch's default). Returns the
    count in effect."""
    check_threads(threads)
    return threads_module.set_threads(threads, op_flop)


#: What a recipe makes in its run directory before its stages record the settings: its log
#: (``run.log``) and its logger's folder (``logs``). A directory that holds anything else but
#: no run's record is refused (:func:`rcvae_torchrl.stages.check_run_directory`).
RUN_MADE = ("run.log", "logs")


def run_dir_refusal(error: Exception, run_dir: str | Path, profile: str) -> SystemExit:
    """The ``error:`` line of a refused ``run_dir``; where it was made with another profile
    (its ``run.log``, whose every run begins ``profile=...``, says so) the line names it: a
    forgotten ``profile=quick`` otherwise reads as a dozen settings that differ."""
    line = f"error: {error}"
    log = Path(run_dir) / "run.log"
    made = re.findall(r"\bprofile=(\S+)", log.read_text(errors="replace")) if log.is_file() else []
    if made and made[-1] != profile and "other settings" in str(error):
        line += (
            f"; its run.log says it was made with profile={made[-1]}, and this run has "
            f"profile={profile}: add profile={made[-1]} to go on with it"
        )
    return SystemExit(line)


#: The folder under ``models/`` of the training checkpoints (``<variant>.pt``): apart from the
#: stage's outputs (``models/*.pt``), which they are not: a finished stage needs none of them,
#: so a missing one is not remade and changes nothing later stages read.
CHECKPOINTS = "checkpoints"

#: The report files both recipes write, named one by one in their report stage's outputs (a
#: pattern such as "*.md" would take a user's notes beside them for the stage's, and remove
#: them when the stage runs again).
REPORT_FILES = (
    "report.md",
    "table.md",
    "table.csv",
    "summary.json",
    "uncertainty_over_time.png",
    "reliability.png",
)


def check_run_settings(config: Any) -> None:
    """The checks that depend on this machine: ``device`` (when the recipe has one),
    ``run_dir`` and ``reuse_from`` (when the recipe has it); call once, before anything is
    created or written."""
    if hasattr(config, "device"):
        resolve_device(config.device)
    check_run_dir(config.run_dir)
    if getattr(config, "reuse_from", None) is not None:
        check_reuse_from(config.reuse_from, config.run_dir)


def check_reuse_from(value: Any, run_dir: str) -> None:
    """Require another run directory than ``run_dir``, one that exists and records its
    settings (``study_config.json``)."""
    path = Path(str(value)).expanduser()
    if not (path / "study_config.json").is_file():
        raise ValueError(
            f"reuse_from: expected a run directory (with its study_config.json), got {value!r}"
        )
    if path.resolve() == Path(run_dir).expanduser().resolve():
        raise ValueError(f"reuse_from: expected another directory than run_dir, got {value!r}")


def _writable(node: Any) -> None:
    """Clear the read-only flag frozen dataclasses give their nodes, so overrides apply."""
    OmegaConf.set_readonly(node, None)
    for key in node:
        child = node._get_node(key)
        if isinstance(child, DictConfig):
            _writable(child)


def _to_object(node: DictConfig, prefix: str) -> Any:
    """The dataclass of ``node``; a range error names its setting by its whole path
    (``agent.distill.epochs``, not ``agent.epochs``): after a failure the nested sections are
    built on their own, to find the one that fails."""
    try:
        return OmegaConf.to_object(node)
    except (ValueError, TypeError) as err:
        for key in node:
            child = node._get_node(key)
            if isinstance(child, DictConfig) and not child._is_none() and not child._is_missing():
                _to_object(child, f"{prefix}{key}.")  # raises when the error is in there
        raise ValueError(f"{prefix}{err}") from None


def _check_known_keys(schema: DictConfig, cfg: Any, prefix: str = "") -> None:
    """Refuse keys the schema does not have, also those added with Hydra's ``+`` (which lets
    them past Hydra's own check: a misspelt ``+seeds=3`` was dropped silently, and
    ``+train.max_step=3`` ended in a FrozenInstanceError)."""
    if not isinstance(cfg, (DictConfig, dict)):
        return
    for key in cfg.keys():
        if key not in schema:
            known = ", ".join(sorted(map(str, schema.keys())))
            raise ValueError(
                f"{prefix}{key}: not a setting of {prefix.rstrip('.') or 'the recipe'} "
                f"(expected one of: {known})"
            )
        child = schema._get_node(key)
        if isinstance(child, DictConfig) and not child._is_missing() and not child._is_none():
            value = cfg[key] if isinstance(cfg, dict) else cfg._get_node(key)
            _check_known_keys(child, value, f"{prefix}{key}.")


def check_override_keys(cls: type, argv: Sequence[str]) -> None:
    """Before Hydra composes anything: a command-line override of a key that the recipe's
    settings ``cls`` do not have ends the run with the recipe's own message, the keys it knows
    (``SystemExit``). Hydra's own message for it suggests adding the key with ``+``, which the
    recipe then refuses (:func:`build_config`). Flags, ``+``/``~`` overrides, config groups
    (``hydra/launcher=...``) and Hydra's own settings are left to Hydra."""
    schema = _schema(cls)
    for arg in argv:
        if arg.startswith(("-", "+", "~")) or "=" not in arg:
            continue
        key = arg.split("=", 1)[0]
        if key.split(".")[0] == "hydra" or "/" in key or "@" in key:
            continue
        override: dict[str, Any] = {}
        node = override
        *parents, leaf = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = None
        try:
            _check_known_keys(schema, override)
        except ValueError as err:
            raise SystemExit(f"error: {err}") from None


def check_printed_config(
    cls: type, argv: Sequence[str], config_dir: Path, config_name: str, profiles: Path
) -> None:
    """Before Hydra runs: with ``--cfg job`` or ``--cfg all`` (not a multirun), Hydra prints
    the composed config and exits without calling the recipe, so a setting out of range would
    be printed as if it ran. Build the settings ``cls`` from the same command line first, with
    the range checks a run makes (not the machine's: a config may be printed for another
    machine), and end with the recipe's own message (``SystemExit``) where one fails. A command
    line Hydra cannot parse or compose is left to Hydra's own message."""
    from hydra import compose, initialize_config_dir
    from hydra._internal.utils import get_args_parser

    try:
        args = get_args_parser().parse_args(list(argv))
    except SystemExit:
        return
    if args.cfg not in ("job", "all") or args.multirun:
        return
    overrides = [o for o in args.overrides if not o.lstrip("+~").startswith(("hydra.", "hydra/"))]
    try:
        with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
            cfg = compose(config_name=config_name, overrides=overrides)
    except Exception:  # Hydra names what it cannot compose when it runs
        return
    try:
        build_config(cls, cfg, profiles, machine=False)
    except (TypeError, ValueError) as error:
        raise SystemExit(f"error: {error}") from None


def _schema(cls: type) -> DictConfig:
    node = OmegaConf.structured(cls)
    _writable(node)
    return node


def register_schema(name: str, cls: type) -> None:
    """Register the dataclass ``cls`` as the Hydra structured config ``name`` (the base of the
    recipe's defaults list, so profiles hold only differences and no key needs ``+``)."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name=name, node=_schema(cls))


def build_config(
    cls: type[T], cfg: DictConfig | dict, profiles: Path | None = None, machine: bool = True
) -> T:
    """The typed, range-checked ``cls`` of a composed config (or a mapping of overrides).

    A mapping that names a ``profile`` gets that profile's settings (``<profiles>/<name>.yaml``)
    under its own, as Hydra composes them: ``{"profile": "quick"}`` is the quick profile, not
    the defaults under its name; an unknown profile is refused. Each section is built on its
    own, so an error names the section and the setting (``train.window: ...``); then, with
    ``machine``, :func:`check_run_settings`.
    """
    if profiles is not None and not isinstance(cfg, DictConfig):
        name = cfg.get("profile", "default")
        check_profile(name, profiles)
        cfg = OmegaConf.merge(OmegaConf.load(Path(profiles) / f"{name}.yaml"), cfg)
    schema = _schema(cls)
    _check_known_keys(schema, cfg)
    try:
        merged = OmegaConf.merge(schema, cfg)
    except Exception as err:  # OmegaConf's ValidationError names the key and the value
        raise ValueError(f"{err}") from None
    sections = {}
    for f in dataclasses.fields(cls):
        node = merged[f.name]
        if isinstance(node, DictConfig):
            sections[f.name] = _to_object(node, f"{f.name}.")
        else:
            sections[f.name] = node
    for name in ("run_dir", "reuse_from"):  # checked and used as the same folder
        if isinstance(sections.get(name), str):
            sections[name] = os.path.expanduser(sections[name])
    config = cls(**sections)
    if machine:
        check_run_settings(config)
    return config


def check_command_line(cls: type, argv: Sequence[str], profiles: Path, config_name: str) -> None:
    """A recipe's checks of its command line before Hydra runs: unknown keys
    (:func:`check_override_keys`), and the settings that ``--cfg job`` would print
    (:func:`check_printed_config`); ``profiles`` is the recipe's ``conf/profile``."""
    check_override_keys(cls, argv)
    check_printed_config(cls, argv, Path(profiles).parent, config_name, profiles)


def typed_settings(study_config: Callable[[Any], T], cfg: DictConfig) -> T:
    """``study_config(cfg)``, or the recipe's ``error:`` line (``SystemExit``, no traceback)
    for a setting out of range."""
    try:
        return study_config(cfg)
    except (TypeError, ValueError) as error:
        raise SystemExit(f"error: {error}") from None


def claim_run_dir(run_dir: str | Path, settings: dict[str, Any], profile: str) -> None:
    """Before anything is made in ``run_dir``: a directory of other ``settings``, or of files
    of the user's own, ends the run with :func:`run_dir_refusal`'s line."""
    from rcvae_torchrl.stages import check_run_directory

    try:
        check_run_directory(run_dir, settings, made_before=RUN_MADE)
    except ValueError as error:
        raise run_dir_refusal(error, run_dir, profile) from None


def say_checks(summary: dict[str, Any], run_dir: str | Path, say: Callable[[str], None]) -> None:
    """The last lines of a run: each of its report's checks (``ok`` or ``NO``, its value) and
    where the report is."""
    for name, check in summary["report"]["checks"].items():
        value = check["value"]
        shown = f"{value:.3f}" if isinstance(value, float) else value
        say(f"{'ok ' if check['met'] else 'NO '} {name}: {shown}")
    say(f"report: {run_dir}/report.md")
