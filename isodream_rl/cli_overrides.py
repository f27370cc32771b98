"""What ``isodream-train`` checks in its command line before Hydra runs, so that a mistyped name is one line.

Hydra reports an unknown group option (``env=dmc_walker_wlak``, ``size=huge``) or a value of the wrong type in
14 to 63 lines with exit status 1, and it takes ``+train.totl_steps=300`` (a key appended to a section) without a
word: the run trains with the default and ignores the key. :func:`check_overrides` refuses, as a
:class:`~isodream_rl.trainers.config.ConfigError` (one line, exit status 2):

- a key under the schema (:class:`~isodream_rl.trainers.config.RunConfig`) that is no setting, with or without
  ``+``/``++``, naming the closest setting and the valid ones;
- a group option that does not exist, naming the closest and the valid ones (a former ``algo`` name, its new one:
  :data:`~isodream_rl.trainers.renames.RENAMED_ALGOS`);
- whatever else composing the configuration as Hydra will refuses (a value of the wrong type), in one line;
- a flag that is none of Hydra's (``--steps 300``: Hydra prints its usage block), naming the flag and the closest
  setting.

Keys inside the free-form settings (``env.kwargs``, ``train.slurm_kwargs``) are left to what reads them,
``hydra.*`` to Hydra. Such a key is an argument of the env (or of the SLURM executor), so it is accepted whether
or not the env group writes it: :func:`free_form_overrides` gives ``env.kwargs.contact_penalty=0.0`` to Hydra as
``++env.kwargs.contact_penalty=0.0``, where Hydra alone would refuse a key its group did not write ("not in
struct").
"""

from __future__ import annotations

import dataclasses
import typing
from difflib import get_close_matches
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra._internal.utils import get_args_parser
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import OverrideType
from hydra.errors import HydraException, MissingConfigException
from omegaconf.errors import OmegaConfBaseException

from isodream_rl.trainers.config import ConfigError, RunConfig
from isodream_rl.trainers.renames import renamed_algo_error
from isodream_rl.user_errors import DEBUG_FLAG

CONFIGS = Path(__file__).parent / "configs"
#: the config groups (``env=...``, ``size=...``): the folders of ``configs/``
GROUPS = tuple(sorted(p.name for p in CONFIGS.iterdir() if p.is_dir() and not p.name.startswith("_")))
#: command-line flags that take no value and leave the rest of the line to overrides
_PLAIN_FLAGS = ("-m", "--multirun")


def _settings(node: type) -> dict[str, type]:
    """``{field: type}`` of a schema dataclass."""
    hints = typing.get_type_hints(node)
    return {f.name: hints[f.name] for f in dataclasses.fields(node)}


def _all_settings(node: type = RunConfig, prefix: str = "") -> list[str]:
    """Every setting of the schema as a dotted key (the sections' fields, not the sections)."""
    keys = []
    for name, kind in _settings(node).items():
        keys += _all_settings(kind, f"{prefix}{name}.") if dataclasses.is_dataclass(kind) else [prefix + name]
    return keys


def free_form_settings(node: type = RunConfig, prefix: str = "") -> list[str]:
    """The free-form settings of the schema (a dict of the arguments of what reads it), as dotted keys."""
    keys = []
    for name, kind in _settings(node).items():
        if dataclasses.is_dataclass(kind):
            keys += free_form_settings(kind, f"{prefix}{name}.")
        elif typing.get_origin(kind) is dict:
            keys.append(prefix + name)
    return keys


def free_form_overrides(args: list[str]) -> list[str]:
    """``args`` with each plain override of a key inside a free-form setting (``env.kwargs.<key>=<value>``) given
    as ``++`` (set it, or add it): the key is an argument of the env whether or not the env group writes it."""
    prefixes = tuple(f"{key}." for key in free_form_settings())
    return ["++" + arg if arg.startswith(prefixes) and "=" in arg else arg for arg in args]


def unknown_setting(key: str) -> str | None:
    """Why the dotted ``key`` is no setting of the schema, or ``None`` when it is one (or lies inside a
    free-form setting such as ``env.kwargs``)."""
    if key.startswith("model.overrides."):  # the world model's fields were under model.overrides before
        return f"model.overrides is no more: set the world model's field as model.{key.split('.', 2)[2]}"
    node, done = RunConfig, []
    for part in key.split("."):
        if not dataclasses.is_dataclass(node):
            return None
        settings = _settings(node)
        if part not in settings:
            section = ".".join(done)
            everywhere = _all_settings()
            by_name = {setting.rpartition(".")[2]: setting for setting in everywhere}
            close = get_close_matches(key, everywhere, 1) or [
                by_name[name] for name in get_close_matches(part, list(by_name), 1)
            ]
            where = f"{section} has no setting {part!r}" if section else f"{part!r} is no setting"
            return (
                where
                + (f" (did you mean {close[0]}?)" if close else "")
                + (f"; the settings of {section}: " if section else "; the settings: ")
                + ", ".join(settings)
                + ("" if section else f", and the groups {', '.join(GROUPS)}")
            )
        done.append(part)
        node = settings[part]
    return None


def _group_error(err: MissingConfigException, line: str, value: str) -> str:
    group = (err.missing_cfg_file or "").split("/")[0]
    renamed = renamed_algo_error(value) if group == "algo" else None
    if renamed:
        return renamed
    options = list(err.options or [])
    close = get_close_matches(value, options, 1)
    return (
        f"{line}: the {group} group has no config {value!r}"
        + (f" (did you mean {group}={close[0]}?)" if close else "")
        + f"; valid: {', '.join(options)}"
    )


def _first_line(err: BaseException) -> str:
    return next((line.strip() for line in str(err).splitlines() if line.strip()), type(err).__name__)


def unknown_flag(args: list[str]) -> str | None:
    """The first argument of ``args`` that looks like a flag (starts with ``-``) but is none of Hydra's
    (``--help``, ``--cfg job``, ``-m``, ...) nor ``--debug``, if any."""
    known = get_args_parser()._option_string_actions  # Hydra's flags, as its own parser reads them
    return next(
        (arg for arg in args if arg.startswith("-") and arg.partition("=")[0] not in {*known, DEBUG_FLAG}),
        None,
    )


def _flag_problem(flag: str) -> str:
    """One line on the unknown ``flag``: the closest setting, and how settings are given."""
    name, _, value = flag.partition("=")
    by_name = {setting.rpartition(".")[2]: setting for setting in _all_settings()}
    close = get_close_matches(name.lstrip("-").replace("-", "_"), list(by_name), 1)
    return (
        f"unknown flag {flag}"
        + (f" (did you mean {by_name[close[0]]}={value or '...'}?)" if close else "")
        + ": settings are key=value overrides (train.total_steps=300, size=tiny); "
        "isodream-train --help lists them"
    )


def check_overrides(args: list[str]) -> None:
    """Check the Hydra overrides ``args`` of ``isodream-train`` (see the module docstring); a command line with
    Hydra's other flags is left to Hydra, a sweep is checked for its keys only.

    Raises:
        ConfigError: one line naming the override or flag, what is wrong and the valid names.
    """
    flag = unknown_flag(args)
    if flag is not None:
        raise ConfigError(_flag_problem(flag))
    if any(arg.startswith("-") and arg not in _PLAIN_FLAGS for arg in args):
        return
    lines = [arg for arg in args if arg not in _PLAIN_FLAGS]
    try:
        overrides = OverridesParser.create().parse_overrides(lines)
    except HydraException as err:
        raise ConfigError(f"invalid override: {_first_line(err)}") from err
    for override in overrides:
        key = override.key_or_group
        if key.split(".")[0].split("/")[0] == "hydra" or (key in GROUPS and "." not in key):
            continue
        if override.type == OverrideType.DEL and key.split(".")[0] in GROUPS:
            continue
        problem = unknown_setting(key)
        if problem:
            raise ConfigError(f"{override.input_line}: {problem}")
    if len(lines) != len(args) or any(o.is_sweep_override() for o in overrides):
        return  # a sweep: Hydra composes each of its runs
    plain = [o.input_line for o in overrides if o.key_or_group.split(".")[0].split("/")[0] != "hydra"]
    try:
        with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
            compose(config_name="config", overrides=plain)
    except MissingConfigException as err:
        group, _, value = (err.missing_cfg_file or "").partition("/")
        line = next(
            (
                o.input_line
                for o in reversed(overrides)
                if o.key_or_group == group and str(o.value()) == value
            ),
            f"{group}={value}",
        )
        raise ConfigError(_group_error(err, line, value)) from err
    except (HydraException, OmegaConfBaseException) as err:
        cause = f": {_first_line(err.__cause__)}" if err.__cause__ is not None else ""
        raise ConfigError(f"{_first_line(err)}{cause}") from err
