"""LightningCLI for ``dapm-lightning {fit,validate,test,predict}``."""

from __future__ import annotations

import difflib
import importlib
import inspect
import os
import re
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

import lightning as L
import torch
import yaml
from lightning.pytorch.callbacks import BasePredictionWriter, DeviceStatsMonitor, LearningRateMonitor
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI, SaveConfigCallback
from lightning.pytorch.trainer.states import TrainerStatus
from lightning.pytorch.utilities import rank_zero_info, rank_zero_only

from dapm_lightning.data.datamodules import DAPMDataModule
from dapm_lightning.data.files import check_folder_writable
from dapm_lightning.models.config import DAPMConfig
from dapm_lightning.training.checkpoint_files import (
    CheckpointReadError,
    UnsafeCheckpointError,
    check_dapm_checkpoint,
    fetch_checkpoint,
    is_lightning_checkpoint_word,
    is_remote,
    is_split_checkpoint,
    join_split_checkpoint_file,
    local_path,
    read_checkpoint,
    remove_unfinished_saves,
)
from dapm_lightning.training.checkpointing import (
    enforce_safe_checkpoint_io,
    find_last_checkpoint,
    fit_checkpoints_summary,
    resolve_last_checkpoint,
)
from dapm_lightning.training.module import DAPMModule
from dapm_lightning.training.quiet import quiet_lightning
from dapm_lightning.training.signals import stop_started_processes


class WeightsOnlyCheckpointError(ValueError):
    """``fit --ckpt_path`` given a checkpoint without training state (e.g. a shipped model's weights)."""

    explained = True


class RunFolderInUseError(ValueError):
    """A new ``fit`` (no ``--ckpt_path``) whose checkpoint folders hold an earlier run's: it would write over them.

    Without a logger: ``trainer.default_root_dir``; with one: a checkpoint callback's fixed ``dirpath``.
    """

    explained = True


class PredictSetupError(ValueError):
    """``predict`` with a data module or callbacks that would predict nothing to disk (a training config)."""

    explained = True


class NoWeightsError(ValueError):
    """``validate``, ``test`` or ``predict`` with no trained weights to run: no checkpoint found, none given."""

    explained = True


TRAINER_DEFAULTS = {"plugins": [{"class_path": "dapm_lightning.training.checkpointing.SafeCheckpointIO"}]}
"""Checkpoints load with ``weights_only=True`` and save atomically. A ``--trainer.plugins`` value replaces this list:
:meth:`DAPMCLI.instantiate_trainer` then puts the safe I/O back (``enforce_safe_checkpoint_io``)."""

FETCHED = "fetched"
"""Where under ``trainer.default_root_dir`` a remote ``--ckpt_path`` (``http(s)://``, fsspec) is downloaded."""

SUBCOMMANDS = ("fit", "validate", "test", "predict")
EVALUATION_SUBCOMMANDS = ("validate", "test", "predict")
"""Subcommands that fall back to the CPU when the config asks for GPUs and there are none."""

CPU_FALLBACK = {"accelerator": "cpu", "devices": 1, "strategy": "auto", "sync_batchnorm": False, "num_nodes": 1}
"""The trainer settings validate/test/predict use instead of a GPU config's on a machine without a GPU."""

UNTRAINED_OUTPUT = {"validate": "metrics", "test": "metrics", "predict": "depth and poses"}
"""What ``validate``, ``test`` and ``predict`` would report from random weights (their refusal says so)."""

EXIT_USAGE = 2
"""Exit status of a command line the parser refuses (argparse's)."""

_UNKNOWN = re.compile(r"unrecognized arguments: (?P<args>.*)")
_GROUP_OPTION = re.compile(r"(?:Group|Subcommand) '(?P<group>[\w.]+)' does not accept (?:nested key|option) "
                           r"'(?P<key>[\w.]+)'")
_IN_CLASS = r"Parser key \"(?P<key>[\w.]+)\":(?:.|\n)*?Problem with given class_path '(?P<class_path>[\w.]+)':"
"""jsonargparse's report on a setting under a ``class_path`` (``data.init_args.NAME``)."""
_INIT_ARG = re.compile(_IN_CLASS + r"\s*(?:Option|Key) '(?P<name>\w+)' is not (?:accepted|expected)")
_KEY_VALUE = re.compile(r"Parser key \"(?P<key>[\w.]+)\":\s*Expected a <class '(?P<type>\w+)'>\. "
                        r"Got value: (?P<value>[^\n]*)")
_INIT_VALUE = re.compile(_IN_CLASS + r"\s*Parser key \"(?P<name>\w+)\":\s*(?P<problem>[^\n]+)")
_NO_CLASS = re.compile(_IN_CLASS + r"\s*module '(?P<module>[\w.]+)' has no attribute '(?P<name>\w+)'")
"""A ``class_path`` that cannot be imported: a typo in the class' (or a module's) name."""


class DAPMArgumentParser(LightningArgumentParser):
    """LightningCLI's parser with short errors, no abbreviated options and loggers that follow the run's folder.

    - A command line it refuses ends in a few lines: the error, the closest valid options for an unknown one
      (``--trainer.max_stpes`` -> ``--trainer.max_steps``) and the ``--help`` to run; not the usage of every
      option. Exit status 2.
    - Abbreviations are refused (``allow_abbrev=False``): ``--trainer.max_step`` is not ``--trainer.max_steps``.
    - A logger without ``save_dir`` (``TensorBoardLogger``, ``CSVLogger``) writes under
      ``trainer.default_root_dir`` (the current directory when unset), whatever file or option set it.
    """

    requested_subcommand: str | None = None
    """The subcommand on the command line (set by :class:`DAPMCLI`), for the ``--help`` an error points to."""
    config_files: tuple[str, ...] = ()
    """The ``--config`` files on the command line (set by :class:`DAPMCLI`), for naming one that is not YAML."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str, ex: Exception | None = None) -> NoReturn:
        if not self.exit_on_error:  # a nested parse: the parser above reports it
            super().error(message, ex)
        parser = getattr(ex, "subcommand_parser", None) or self
        subcommand = getattr(parser, "subcommand", None) or self.requested_subcommand
        if "Problems parsing config" in message and (broken := unreadable_yaml(self.config_files)):
            message = broken
        print(short_parse_error(message, option_strings(parser), subcommand, self.config_files), file=sys.stderr)
        sys.exit(EXIT_USAGE)

    def validate(self, *args: Any, **kwargs: Any) -> None:
        namespace = args[0] if args else kwargs.get("namespace", kwargs.get("cfg"))
        if namespace is not None:
            loggers_follow_root_dir(namespace)
        super().validate(*args, **kwargs)


def unreadable_yaml(paths: Sequence[str]) -> str | None:
    """``FILE: not valid YAML (line L, column C): PROBLEM`` and the fix, for the first of ``paths`` that is not."""
    for path in paths:
        try:
            yaml.safe_load(Path(path).read_text())
        except yaml.MarkedYAMLError as error:
            mark = error.problem_mark
            where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
            return (f"{path}: not valid YAML{where}: {error.problem or error}\n"
                    f"  fix: correct the file there (indentation with spaces, a ':' after each key, brackets closed)")
        except (OSError, UnicodeDecodeError, yaml.YAMLError):
            continue  # not there (the parser's own message says so) or not text (config_file_problem says so)
    return None


CHECKPOINT_SUFFIXES = (".ckpt", ".pt", ".pth", ".bin", ".safetensors")
"""Suffixes of model files: given as ``--config``, the fix names ``--ckpt_path``."""


def config_file_problem(path: str) -> str | None:
    """``FILE: what is wrong`` and the fix, for a ``--config`` file that cannot hold settings; None otherwise.

    Not UTF-8 text (a checkpoint, an image), empty (or comments only), or YAML that is not a mapping of settings
    (a list, a bare word). None for a file that is fine, missing or unreadable (the parser names those), or not
    valid YAML (:func:`unreadable_yaml` names the line).
    """
    file = Path(path)
    try:
        if not file.is_file():
            return None
        data = file.read_bytes()
    except OSError:
        return None
    fix = "  fix: give --config a YAML file of settings (trainer:, model:, data: ...), e.g. a run's config.yaml"
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as error:
        model = file.suffix.lower() in CHECKPOINT_SUFFIXES or data[:2] == b"PK"  # torch.save writes a zip
        return (f"{path}: not a YAML text file (byte {error.start} is not UTF-8 text: "
                f"{'a checkpoint or other binary file' if model else 'a binary file'})\n"
                + (f"  fix: a checkpoint goes to --ckpt_path {path} (or --model.init_weights {path} to fine-tune "
                   "from its weights); --config takes a YAML file of settings" if model else fix))
    try:
        loaded = yaml.safe_load(text)
    except yaml.YAMLError:
        return None
    if loaded is None:
        what = "only comments" if text.strip() else "the file is empty"
        return f"{path}: no settings in it ({what})\n{fix}, or leave out --config {path}"
    if not isinstance(loaded, dict):
        kind = "a list" if isinstance(loaded, list) else f"a single value ({str(loaded)[:40]!r})"
        return f"{path}: not a mapping of settings (the file holds {kind})\n{fix}"
    if (twice := repeated_key(text)) is not None:
        key, first, second = twice
        return (f"{path}: {key} is set twice (lines {first} and {second}); YAML would keep the second silently\n"
                f"  fix: keep one of the two lines")
    return None


def repeated_key(text: str) -> tuple[str, int, int] | None:
    """The first key set twice in one mapping of the YAML ``text``: ``(dotted key, first line, second line)``."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return None

    def walk(node: Any, prefix: str) -> tuple[str, int, int] | None:
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, int] = {}
            for key_node, value_node in node.value:
                key = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
                line = key_node.start_mark.line + 1
                if key is not None and key in seen:
                    return f"{prefix}{key}", seen[key], line
                if key is not None:
                    seen[key] = line
                if (found := walk(value_node, f"{prefix}{key}.")) is not None:
                    return found
        elif isinstance(node, yaml.SequenceNode):
            for index, item in enumerate(node.value):
                if (found := walk(item, f"{prefix[:-1]}[{index}].")) is not None:
                    return found
        return None

    return walk(root, "")


def option_strings(parser: Any) -> list[str]:
    """Every ``--option`` a parser and its subcommands accept (a subclass' init args are not listed)."""
    parsers = [parser]
    subcommands = getattr(parser, "_subcommands_action", None)
    parsers += list(getattr(subcommands, "_name_parser_map", {}).values())
    return sorted({s for p in parsers for action in p._actions for s in action.option_strings if s.startswith("--")})


def _init_options(class_path: str, key: str) -> list[str]:
    """``--KEY.init_args.NAME`` for every parameter of the class ``class_path`` ([] when it cannot be imported)."""
    module_name, _, name = class_path.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module_name), name)
    except (ImportError, AttributeError, ValueError):
        return []
    names: list[str] = []
    for klass in (k for k in cls.__mro__ if "__init__" in vars(k)):  # **kwargs: the base class' parameters too
        try:
            parameters = inspect.signature(klass.__init__).parameters.values()
        except (TypeError, ValueError):
            break
        names += [p.name for p in parameters if p.name != "self" and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
        if not any(p.kind == p.VAR_KEYWORD for p in parameters):
            break
    return [f"--{key}.init_args.{n}" for n in dict.fromkeys(names)]


def closest(option: str, options: Sequence[str], count: int = 3) -> list[str]:
    """The valid options nearest to ``option`` (difflib), those nearly as near as the nearest one only."""
    scored = sorted(((difflib.SequenceMatcher(None, option, o).ratio(), o) for o in options), reverse=True)
    best = scored[0][0] if scored else 0.0
    return [o for ratio, o in scored[:count] if ratio >= max(0.6, best - 0.05)]


def _holds(node: Any, value: str) -> bool:
    """Whether a YAML ``node`` is ``value`` (as text) or holds it in its lists and mappings."""
    if isinstance(node, dict):
        node = list(node.values())
    return any(_holds(n, value) for n in node) if isinstance(node, list) else str(node) == value


def files_setting(key: str, config_files: Sequence[str], value: str | None = None) -> list[str]:
    """The config files among ``config_files`` that set the dotted ``key`` (``trainer.max_stpes``).

    With ``value``: only those whose setting is or holds it (a value the parser refused, a class path).
    """
    found = []
    for path in config_files:
        try:
            node: Any = yaml.safe_load(Path(path).read_text())
        except (OSError, ValueError, yaml.YAMLError):
            continue
        for part in key.split("."):
            if not isinstance(node, dict) or part not in node:
                break
            node = node[part]
        else:
            if value is None or _holds(node, value):
                found.append(path)
    return found


def _class_candidates(module_name: str, class_path: str, name: str) -> list[str]:
    """``class_path`` with ``name`` (the part of it ``module_name`` lacks) replaced by the nearest importable names.

    Those are the public classes of that module and of its loaded submodules, or its submodules where ``name`` is
    a module's.
    """
    try:
        module = importlib.import_module(module_name)
    except ImportError:
        return []
    rest = class_path.removeprefix(f"{module_name}.{name}")
    paths: dict[Any, str] = {}  # each class (or submodule) once, by its shortest path
    loaded = [module, *(m for k, m in sorted(sys.modules.items()) if k.startswith(f"{module_name}.") and m)]
    for each in loaded if not rest else [module]:
        prefix = each.__name__.removeprefix(module_name)
        for n, v in vars(each).items():
            if not n.startswith("_") and (inspect.ismodule(v) if rest else inspect.isclass(v)):
                paths.setdefault(v, f"{module_name}{prefix}.{n}")
    best = closest(name, sorted({p.rpartition(".")[2] for p in paths.values()}))
    return sorted(f"{p}{rest}" for p in paths.values() if p.rpartition(".")[2] in best)[:3]


_MISSING_CONFIG = re.compile(r'Parser key "config":\s*(File does not exist|Path is not a file): \'(?P<path>[^\']*)\'')
"""jsonargparse's error for a ``--config`` path that is not a file."""


def short_parse_error(message: str, options: Sequence[str], subcommand: str | None,
                      config_files: Sequence[str] = ()) -> str:
    """``error: ...``, the closest valid options when one is unknown, and the ``--help`` to run.

    An unknown setting names the config file(s) of ``config_files`` that set it.
    """
    unknown: list[str] = []
    options = list(options)
    suggestions: dict[str, list[str]] = {}
    set_in = ""  # the config file(s) that set a value the parser refused
    if match := _UNKNOWN.search(message):
        unknown = [word.split("=", 1)[0] for word in match.group("args").split() if word.startswith("-")]
        message = (f"unknown option{'s' if len(unknown) > 1 else ''} {', '.join(unknown)}" if unknown
                   else f"unexpected argument(s): {match.group('args')}")
    elif match := _GROUP_OPTION.search(message):
        prefix = "" if message.startswith("Subcommand") else match.group("group") + "."
        unknown = [f"--{prefix}{match.group('key')}"]
        holders = files_setting(unknown[0][2:], config_files)
        where = f"set in {', '.join(holders)}" if holders else "in a config file or on the command line"
        message = f"unknown setting {unknown[0][2:]} ({where})"
    elif match := _NO_CLASS.search(message):  # a typo in a class path: the module's nearest classes
        key, class_path, name = match.group("key"), match.group("class_path"), match.group("name")
        holders = files_setting(key, config_files, class_path)
        set_in = f" (set in {', '.join(holders)})" if holders else ""
        message = f"{key}: no class {class_path}: {match.group('module')} has no {name!r}"
        suggestions[class_path] = _class_candidates(match.group("module"), class_path, name)
    elif match := _INIT_ARG.search(message):
        key, class_path, name = match.group("key"), match.group("class_path"), match.group("name")
        unknown = [f"--{key}.init_args.{name}"]
        options = _init_options(class_path, key)
        holders = files_setting(f"{key}.init_args.{name}", config_files)
        where = f", set in {', '.join(holders)}" if holders else ""
        message = f"{key}: {class_path.rpartition('.')[2]} has no setting {name!r} ({unknown[0]}{where})"
    elif match := _INIT_VALUE.search(message):  # a value of the wrong type under a class_path (data: the union)
        problem = re.sub(r"Expected a <class '(\w+)'>", r"expected \1", match.group("problem").strip())
        key = f"{match.group('key')}.init_args.{match.group('name')}"
        got = re.search(r"Got value: (.*)$", problem)
        holders = files_setting(key, config_files, got.group(1)) if got else []
        set_in = f" (set in {', '.join(holders)})" if holders else ""
        message = f"--{key}: {problem}"
    elif match := _KEY_VALUE.search(message):  # a value of the wrong type: one line, as the data module's
        holders = files_setting(match.group("key"), config_files, match.group("value"))
        set_in = f" (set in {', '.join(holders)})" if holders else ""
        message = f"--{match.group('key')}: expected {match.group('type')}. Got value: {match.group('value')}"
    if re.search(r"expected float\. Got value: [+-]?(inf(inity)?|nan)\s*$", message, re.IGNORECASE):
        message = message.replace("expected float.", "expected a finite number.")
    lines = [f"error: {message.strip()}{set_in}"]
    if missing := _MISSING_CONFIG.search(message):  # --config naming no file (a typo, a folder)
        path = Path(missing.group("path"))
        what = "a folder, not a config file" if path.is_dir() else "no such file"
        lines = [f"error: --config {path}: {what}",
                 f"  fix: give a YAML config file (relative paths start from the current directory, {os.getcwd()}); "
                 "the shipped ones: configs/paper/*.yaml, configs/ablations/*.yaml, "
                 "dapm_lightning/configs/quickstart.yaml"]
    suggestions.update({option: closest(option, options) for option in unknown})
    for option, found in suggestions.items():
        if found:
            lines.append(f"  {option}: did you mean {', '.join(found)}?")
    lines.append(f"see `dapm-lightning {subcommand or 'fit'} --help` for every option")
    return "\n".join(lines)


def stacked_run_folder(configs: Sequence[str], words: Sequence[str], subcommand: str | None = None) -> str | None:
    """The run folder of a stack of config files: the first file's ``trainer.default_root_dir`` + ``+NAME`` per overlay.

    ``--config configs/paper/uapd_dapm.yaml --config configs/ablations/t9_pqb_only.yaml`` runs in
    ``outputs/uapd_dapm+t9_pqb_only``: each stack in a folder of its own, so that ``--ckpt_path last`` resumes that
    stack's run, never the base config's or another stack's. None (nothing changed) for one file, when the command
    line or a later file sets ``trainer.default_root_dir``, when the first file sets none, or for ``predict`` (its
    outputs have their own folder).
    """
    if len(configs) < 2 or subcommand == "predict" or any(w.split("=", 1)[0] == "--trainer.default_root_dir"
                                                           for w in words):
        return None
    roots = []
    for path in configs:
        try:
            loaded = yaml.safe_load(Path(path).read_text())
        except (OSError, yaml.YAMLError):
            return None  # the parser names the file
        trainer = loaded.get("trainer") if isinstance(loaded, dict) else None
        roots.append(trainer.get("default_root_dir") if isinstance(trainer, dict) else None)
    if roots[0] is None or any(root is not None for root in roots[1:]):
        return None
    return str(roots[0]) + "".join(f"+{Path(path).stem}" for path in configs[1:])


def loggers_follow_root_dir(config: Any) -> None:
    """Set the ``save_dir`` of every logger that has none to ``trainer.default_root_dir`` (in place).

    ``config`` is a subcommand's configuration or the whole one (with ``fit``, ``test``... branches).
    """
    for prefix in ("", *(f"{name}." for name in SUBCOMMANDS)):
        trainer = config.get(prefix + "trainer") if hasattr(config, "get") else None
        if trainer is None or not hasattr(trainer, "get"):
            continue
        root = trainer.get("default_root_dir") or "."
        for logger in _as_list(trainer.get("logger")):
            init_args = logger.get("init_args") if hasattr(logger, "get") else None
            if init_args is not None and "save_dir" in init_args and init_args.get("save_dir") is None:
                init_args["save_dir"] = str(root)


class SaveConfigOfRun(SaveConfigCallback):
    """Saves the resolved config into the run's log folder, as ``config.yaml`` (fit) or ``config_SUBCOMMAND.yaml``.

    ``config_validate.yaml`` and ``config_test.yaml`` for validate and test: so an evaluation never replaces the
    ``config.yaml`` of a fit that logs into the same folder (without a logger, ``trainer.default_root_dir``), which
    the fit resumes from. Not for predict: its outputs go to the prediction writer's folder, and without a logger
    Lightning's log folder would be the current directory.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.fit_filename = self.config_filename
        self.saved_path = ""
        """Where the config was saved ("" before :meth:`setup` saves it); what ``fit``'s closing lines name."""

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage == "predict":
            return
        name, subcommand = Path(self.fit_filename), getattr(stage, "value", stage)  # a TrainerFn: its value
        self.config_filename = name.name if subcommand == "fit" else f"{name.stem}_{subcommand}{name.suffix}"
        saves = self.save_to_log_dir and not self.already_saved
        log_dir = trainer.log_dir if saves else None  # broadcast in every process, as the parent's setup does
        super().setup(trainer, pl_module, stage)
        if saves and log_dir is not None:
            self.saved_path = os.path.join(log_dir, self.config_filename)


def needs_logger(callback: Any) -> bool:
    """Whether a callback fails or does nothing without a logger.

    Lightning's ``LearningRateMonitor`` and ``DeviceStatsMonitor`` raise; a callback with a ``needs_logger``
    attribute (``DepthPanelLogger`` without ``output_dir``) says so itself.
    """
    return isinstance(callback, (LearningRateMonitor, DeviceStatsMonitor)) or bool(getattr(callback, "needs_logger",
                                                                                            False))


class DAPMCLI(LightningCLI):
    """LightningCLI with DAPM's module and any :class:`DAPMDataModule` subclass (``--data.class_path``).

    With ``--ckpt_path``, the checkpoint is read safely (``weights_only``; a damaged file is named, and a file
    that is not a dapm-lightning checkpoint is refused saying what it is). ``validate``, ``test`` and
    ``predict`` then build the checkpoint's own model (its saved settings override the configuration's).
    ``fit`` resumes only into the same architecture: what differs is listed with the fix, instead of a shape
    error deep inside ``load_state_dict`` or a silent switch to the checkpoint's settings. ``validate``, ``test``
    and ``predict`` without trained weights (no ``--ckpt_path`` nor ``model.init_weights``, or ``--ckpt_path last``
    finding no complete checkpoint) are refused (:class:`NoWeightsError`) instead of running an untrained network.

    Also: short errors for a command line the parser refuses (:class:`DAPMArgumentParser`); ``validate``,
    ``test`` and ``predict`` of a GPU config run on the CPU of a machine without a GPU (``fit`` refuses,
    naming the settings); without a logger (``--trainer.logger false``) the callbacks that need one are left
    out, each run says which.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("parser_class", DAPMArgumentParser)
        super().__init__(*args, **kwargs)

    def parse_arguments(self, parser: LightningArgumentParser, args: Any) -> None:
        words = sys.argv[1:] if args is None else list(args) if isinstance(args, (list, tuple)) else []
        if isinstance(parser, DAPMArgumentParser):
            parser.requested_subcommand = next((w for w in words if w in SUBCOMMANDS), None)
            configs = tuple([b for a, b in zip(words, words[1:]) if a == "--config"]
                            + [w.split("=", 1)[1] for w in words if w.startswith("--config=")])
            subcommands = getattr(parser, "_subcommands_action", None)
            # absolute: the parser reads a config from its own folder (os.chdir), where a relative path is not there
            absolute = tuple(os.path.abspath(config) for config in configs)
            for each in [parser, *getattr(subcommands, "_name_parser_map", {}).values()]:  # a subcommand reports
                each.config_files = absolute
            for config in configs:  # a binary or empty file: named before the parser's decoding error or bare report
                if (problem := config_file_problem(config)) is not None:
                    parser.error(problem)
            folder = stacked_run_folder(configs, words, parser.requested_subcommand)
            if folder is not None and args is None:  # LightningCLI reads sys.argv (and warns when given both)
                sys.argv = [sys.argv[0], *words, "--trainer.default_root_dir", folder]
            elif folder is not None:
                args = [*words, "--trainer.default_root_dir", folder]
        super().parse_arguments(parser, args)

    def _run_subcommand(self, subcommand: str) -> None:
        """Run it; when it fails here, stop the DDP processes this one started (they would wait for it).

        A stop by SIGTERM or Ctrl-C (``SystemExit``) is not a failure: every process stops after the same step
        and exits on its own.
        """
        try:
            super()._run_subcommand(subcommand)
        except SystemExit:
            raise
        except BaseException:
            if killed := stop_started_processes(getattr(self, "trainer", None)):
                print(f"stopped the {len(killed)} other training process(es) of this run (pid "
                      f"{', '.join(map(str, killed))}): they were waiting for this one", file=sys.stderr)
            raise

    def _parse_ckpt_path(self) -> None:
        """Find, fetch and check ``--ckpt_path`` before anything is built, and take the checkpoint's settings.

        ``last``: the newest complete checkpoint of the run (:meth:`_resolve_last`). An address (``http(s)://``,
        another fsspec path): downloaded into ``DEFAULT_ROOT_DIR/fetched/`` (every time, named after the whole
        address) and read from there like a local file; a ``file://`` path is the local file; a split checkpoint folder
        (``checkpoint_files.split_checkpoint``) is joined, checked, into ``DEFAULT_ROOT_DIR/fetched/``. The file is read
        once, safely (``weights_only``: a file holding pickled code is refused without running it, a damaged
        one is named), checked to be a dapm-lightning checkpoint, and for ``fit`` of the same architecture; its
        ``hyper_parameters`` then override the configuration's model, as LightningCLI does. ``fit`` also removes
        the temporary files of saves that were killed in the run's folders.
        """
        subcommand = self.config.get("subcommand")
        if not subcommand:
            return
        config = self.config[subcommand]
        if subcommand == "fit" and getattr(rank_zero_only, "rank", 0) == 0:
            remove_unfinished_saves(self._run_folders(config, current_directory=False)[0])
        ckpt_path = given = config.get("ckpt_path")
        self.ckpt_path_given = given
        """``--ckpt_path`` as the user gave it (``last`` stays ``last`` when it finds nothing or only damaged files)."""
        checkpoint: Any = None
        fetched_from: str | None = None
        if ckpt_path == "last":
            found = self._resolve_last(config, subcommand)
            if found is None:
                return  # fit: a first run starts from scratch (the others are refused in _resolve_last)
            ckpt_path, checkpoint = found
        elif ckpt_path and is_remote(ckpt_path):
            trainer = config.get("trainer") or {}
            fetched_from = str(ckpt_path)
            ckpt_path = str(fetch_checkpoint(fetched_from, Path(trainer.get("default_root_dir") or ".") / FETCHED))
        elif ckpt_path and is_split_checkpoint(ckpt_path):  # Lightning reads a file: join the parts into one
            root = Path((config.get("trainer") or {}).get("default_root_dir") or ".")
            ckpt_path = str(join_split_checkpoint_file(ckpt_path, root / FETCHED))
        elif ckpt_path and str(ckpt_path).startswith("file://"):
            ckpt_path = str(local_path(ckpt_path))
        if not ckpt_path and subcommand in EVALUATION_SUBCOMMANDS and not config.get("model", {}).get("init_weights"):
            last = ("" if subcommand == "predict" else ", or --ckpt_path last for the newest checkpoint under the "
                    f"run's trainer.default_root_dir ({self._run_folders(config)[0][0]})")
            raise NoWeightsError(
                f"{subcommand}: no weights to {subcommand} with: neither --ckpt_path nor --model.init_weights is "
                f"given, and an untrained network's {UNTRAINED_OUTPUT[subcommand]} would mean nothing.\nFix: "
                "--ckpt_path CKPT (a checkpoint written by `dapm-lightning fit`, or a shipped model such as "
                f"models/dapm-synthetic-r18-256){last}.")
        if not ckpt_path or (not Path(ckpt_path).is_file() and is_lightning_checkpoint_word(str(ckpt_path))):
            return  # Lightning's own values (best, hpc, registry...)
        config["ckpt_path"] = str(ckpt_path)
        if checkpoint is None:
            try:
                checkpoint = read_checkpoint(ckpt_path)  # refused pickles and damaged files: named, with the fix
            except (UnsafeCheckpointError, CheckpointReadError) as error:
                if fetched_from is None:
                    raise
                Path(ckpt_path).unlink(missing_ok=True)  # a refused download is not kept
                where = f"{fetched_from} (fetched into {ckpt_path}, now removed)"
                error.args = (str(error).replace(str(ckpt_path), where, 1),)  # the same error (its fix kept)
                raise
        check_dapm_checkpoint(checkpoint, ckpt_path)  # another model's, a bare state dict: what it is, the fix
        if subcommand == "fit" and "optimizer_states" not in checkpoint:
            raise WeightsOnlyCheckpointError(
                f"{given}: holds the model's weights only (no optimizer or loop state), so `fit` "
                "cannot resume from it.\nFix: use it with `predict`, `test`, `validate` or `export`; to fine-tune "
                f"from its weights, `--model.init_weights {given}` instead of --ckpt_path; to resume a training, "
                "pass that run's last.ckpt (or --ckpt_path last).")
        saved = checkpoint.get("hyper_parameters", {}).get("net")
        net = config.get("model", {}).get("net")
        if subcommand == "fit" and saved is not None and net is not None:
            current = DAPMConfig.from_dict(net.as_dict() if hasattr(net, "as_dict") else dict(net))
            current.check_loads(saved, str(ckpt_path))
        self._apply_checkpoint_settings(checkpoint, subcommand)

    def _apply_checkpoint_settings(self, checkpoint: dict[str, Any], subcommand: str) -> None:
        """The checkpoint's ``hyper_parameters`` over the configuration's model.

        LightningCLI's ``_parse_ckpt_path``, from the checkpoint already read instead of a second ``torch.load``.
        """
        hparams = dict(checkpoint.get("hyper_parameters") or {})
        hparams.pop("_instantiator", None)
        if not hparams:
            return
        if "_class_path" in hparams:
            hparams = {"class_path": hparams.pop("_class_path"), "dict_kwargs": hparams}
        try:
            self.config = self.parser.parse_object({subcommand: {"model": hparams}}, self.config)
        except SystemExit:
            sys.stderr.write("Parsing of ckpt_path hyperparameters failed!\n")
            raise

    def before_fit(self) -> None:
        """Read ``model.init_weights`` unless ``--ckpt_path`` resumes a run.

        Before the fit: in every process, before the data, sharding or tuning, and a wrong file stops the run early.
        """
        model = self.model
        resumes = self.config["fit"].get("ckpt_path")
        self._check_run_folder_writable()
        if not getattr(self, "ckpt_path_given", resumes):  # a run asked to resume continues the one there
            self._refuse_writing_over_a_run()
        if isinstance(model, DAPMModule) and model.init_weights is not None and not resumes:
            model.load_initial_weights()
        self._read_data_early("fit")

    def after_fit(self) -> None:
        """A fit that finished names what it saved, and how to evaluate it (the first process only)."""
        trainer = self.trainer
        if not trainer.is_global_zero or trainer.state.status != TrainerStatus.FINISHED:
            return
        saved = fit_checkpoints_summary(trainer)
        if not saved:
            return
        callbacks: list[L.Callback] = getattr(trainer, "callbacks", [])  # set by Lightning's connector
        config = next((callback.saved_path for callback in callbacks if isinstance(callback, SaveConfigOfRun)), "")
        # the run's own config.yaml, which test can read, as SaveConfigOfRun wrote it (no collective here)
        config = shlex.quote(config) if os.path.isfile(config) else "CONFIG"
        print("\n".join([f"fit finished at step {trainer.global_step}.", *(f"{what}: {path}" for what, path in saved),
                         f"evaluate it: dapm-lightning test --config {config} --ckpt_path {shlex.quote(saved[0][1])}"]),
              flush=True)

    def _refuse_writing_over_a_run(self) -> None:
        """A new ``fit`` whose checkpoint folders hold an earlier run's checkpoints: refused.

        Without a logger (``--trainer.logger false``), every run writes ``DEFAULT_ROOT_DIR/checkpoints/last.ckpt``
        and ``DEFAULT_ROOT_DIR/config.yaml``; with a logger each run writes into a new version folder
        (``tensorboard/version_N/checkpoints``), but a checkpoint callback with a fixed ``dirpath`` writes into that
        folder whatever the version. So a second run would replace the first one's checkpoints. A run that resumes
        (``--ckpt_path``; also ``last`` finding only damaged checkpoints, which then starts afresh in the same folder,
        as documented) continues the one there and is not refused. A remote ``dirpath`` is not looked at. Checked by
        every process before the processes of a DDP run meet, so all refuse alike and none waits for another.
        """
        trainer = self.trainer
        root = Path(trainer.default_root_dir)
        dirpaths = [getattr(callback, "dirpath", None) for callback in trainer.checkpoint_callbacks]
        folders = [Path(dirpath) if dirpath else root / "checkpoints" for dirpath in dirpaths
                   if not (dirpath and is_remote(str(dirpath))) and (dirpath or not trainer.loggers)]
        held = {folder: sorted(folder.glob("*.ckpt")) for folder in dict.fromkeys(folders) if folder.is_dir()}
        found = sorted(path for paths in held.values() for path in paths)
        if not found:
            return
        more = f" and {len(found) - 3} more checkpoint(s)" if len(found) > 3 else ""
        if trainer.loggers:
            where = ", ".join(str(folder) for folder, paths in held.items() if paths)
            raise RunFolderInUseError(
                f"fit: {where} holds the checkpoints of an earlier run ({', '.join(map(str, found[:3]))}{more}); this "
                "run would write over them: a checkpoint callback with a fixed dirpath writes there whatever the log "
                "version.\nFix: resume that run with --ckpt_path last, or give this run a folder of its own: a new "
                "dirpath for the checkpoint callback (or none: each run then checkpoints into its log version folder).")
        config = root / self.save_config_kwargs.get("config_filename", "config.yaml")
        shown = [*found[:3], *([config] if self.save_config_callback and config.is_file() else [])]
        raise RunFolderInUseError(
            f"fit: {root} holds an earlier run without a logger ({', '.join(map(str, shown))}{more}); this run would "
            "write over it, as it writes into the same folders.\nFix: resume that run with --ckpt_path last, or start "
            "this one in a folder of its own: --trainer.default_root_dir NEW_DIR (or with a logger, which gives each "
            "run a new version folder).")

    def before_validate(self) -> None:
        self._check_run_folder_writable()
        self._read_initial_weights("validate")
        self._read_data_early("validate")

    def before_test(self) -> None:
        self._check_run_folder_writable()
        self._read_initial_weights("test")
        self._read_data_early("test")

    def _check_run_folder_writable(self) -> None:
        """A run folder (``trainer.default_root_dir``) that cannot be made or written: refused before any work."""
        root = str(self.trainer.default_root_dir)
        if not is_remote(root):  # Lightning writes file:///x as file:/x, a local folder too
            check_folder_writable(local_path(root), "--trainer.default_root_dir")

    def before_predict(self) -> None:
        self._read_initial_weights("predict")

    @staticmethod
    def _check_predict_setup(config: Any) -> None:
        """``predict`` of a configuration whose data module serves labelled samples, or without a prediction writer.

        A training config (``configs/paper/*.yaml``) has neither: nothing would be written, so it is refused, with
        the two forms that work, before its classes are built (the paper's backbone would be downloaded first).
        """
        def config_class(entry: Any) -> type | None:
            class_path = entry.get("class_path") if hasattr(entry, "get") else None
            module_name, _, name = str(class_path or "").rpartition(".")
            try:
                return getattr(importlib.import_module(module_name), name) if module_name else None
            except (ImportError, AttributeError):
                return None  # the parser names what cannot be imported

        trainer = config.get("trainer") or {}
        data = config_class(config.get("data"))
        missing = []
        if isinstance(data, type) and issubclass(data, DAPMDataModule) and not data.serves_prediction:
            missing.append(f"its data module is {data.__name__}, which serves labelled samples, not PredictDataModule "
                           "(images, folders, videos)")
        callbacks = [config_class(entry) for entry in _as_list(trainer.get("callbacks"))]
        if not any(isinstance(c, type) and issubclass(c, BasePredictionWriter) for c in callbacks):
            missing.append("no prediction writer callback (PredictionWriter) writes its outputs")
        if missing:
            raise PredictSetupError(
                "predict with this configuration would write nothing: " + "; ".join(missing) + ".\nFix: "
                "`dapm-lightning predict SOURCE --ckpt_path CKPT --out OUT`, or `dapm-lightning predict --config "
                "configs/predict.yaml --ckpt_path CKPT --data.init_args.source SOURCE` (a training config's "
                "settings are not needed: the checkpoint's network is built from it); to score a labelled split, "
                "`dapm-lightning test`.")

    def _read_initial_weights(self, subcommand: str) -> None:
        """``validate``, ``test`` or ``predict`` without ``--ckpt_path``: the network's weights from ``init_weights``.

        :meth:`_parse_ckpt_path` refused the run if neither is set: an untrained network is never evaluated.
        """
        model = self.model
        if isinstance(model, DAPMModule) and model.init_weights is not None and not self.config[subcommand].get(
                "ckpt_path"):
            model.load_initial_weights()

    def _read_data_early(self, stage: str) -> None:
        """Scan the data sets before the trainer starts (:meth:`DAPMDataModule.read_early`).

        A wrong root or a broken file then stops the run before the loggers make their version folders.
        """
        if isinstance(self.datamodule, DAPMDataModule):
            self.datamodule.read_early(stage)
        if isinstance(self.model, DAPMModule):  # the depth kind and limit: before the loggers' folders too
            self.model.check_data_agrees(self.datamodule, self.config[stage].get("ckpt_path"))

    def before_instantiate_classes(self) -> None:
        subcommand = self.config.get("subcommand")
        if subcommand == "predict":
            self._check_predict_setup(self.config["predict"])
        trainer = self.config[subcommand].get("trainer") if subcommand else self.config.get("trainer")
        if trainer is not None:
            self._gpu_config_without_gpu(trainer, subcommand)

    @staticmethod
    def _gpu_config_without_gpu(trainer: Any, subcommand: str | None) -> None:
        """validate/test/predict of a GPU config on a machine without one: the CPU, with a note; fit: an error."""
        accelerator = trainer.get("accelerator")
        if not (isinstance(accelerator, str) and accelerator.lower() in ("gpu", "cuda")) or torch.cuda.is_available():
            return
        asked = ", ".join(f"{key} {trainer.get(key)}" for key in ("accelerator", "devices", "num_nodes", "strategy")
                          if trainer.get(key) is not None)
        if subcommand not in EVALUATION_SUBCOMMANDS:
            raise ValueError(f"trainer.accelerator: {accelerator}, but this machine has no GPU "
                             "(torch.cuda.is_available() is False).\nFix: train on a GPU machine, or on the CPU with "
                             "--trainer.accelerator cpu --trainer.devices 1 --trainer.strategy auto "
                             "--trainer.sync_batchnorm false")
        for key, value in CPU_FALLBACK.items():
            trainer[key] = value
        precision = str(trainer.get("precision"))
        if precision.startswith("16"):  # half precision is a GPU setting; bf16 and 32 run on the CPU
            trainer["precision"] = "32-true"
        rank_zero_info(f"note: no GPU on this machine: {subcommand} runs on the CPU, one process (the config asked "
                       f"for {asked})")

    def instantiate_trainer(self, **kwargs: Any) -> L.Trainer:
        """LightningCLI's trainer, with a safe checkpoint I/O whatever ``trainer.plugins`` holds.

        A ``--trainer.plugins`` value (a cluster environment, a precision plugin) replaces the default list, and
        with it :class:`~dapm_lightning.training.checkpointing.SafeCheckpointIO`: it is put back here (or a
        plugin that reads checkpoints its own way is refused, naming it). Without a logger, the callbacks that
        need one are left out.
        """
        trainer = super().instantiate_trainer(**kwargs)
        enforce_safe_checkpoint_io(trainer)
        if not trainer.loggers:
            callbacks: list[L.Callback] = getattr(trainer, "callbacks", [])  # set by Lightning's connector
            dropped = [callback for callback in callbacks if needs_logger(callback)]
            if dropped:
                trainer.callbacks = [callback for callback in callbacks if callback not in dropped]  # type: ignore[attr-defined]
                names = ", ".join(type(callback).__name__ for callback in dropped)
                rank_zero_info(f"note: no logger (trainer.logger false): left out {names}, which need one")
        return trainer

    @staticmethod
    def _run_folders(config: Any, current_directory: bool = True) -> tuple[list[str], list[str]]:
        """``(roots, checkpoint folders)`` of a run.

        Roots: ``trainer.default_root_dir`` (the current directory when unset, unless ``current_directory`` is
        False), every logger's ``save_dir`` and every callback's ``dirpath``; checkpoint folders: the callbacks'
        ``dirpath``.
        """
        trainer = config.get("trainer") or {}
        root = trainer.get("default_root_dir") or ("." if current_directory else None)
        roots = [str(root)] if root else []
        folders: list[str] = []
        for entry in _as_list(trainer.get("logger")) + _as_list(trainer.get("callbacks")):
            init_args = entry.get("init_args") if hasattr(entry, "get") else None
            if init_args is not None and init_args.get("save_dir"):
                roots.append(str(init_args.get("save_dir")))
            if init_args is not None and init_args.get("dirpath"):
                folders.append(str(init_args.get("dirpath")))
        return roots + folders, folders

    @classmethod
    def _resolve_last(cls, config: Any, subcommand: str = "fit") -> tuple[str, dict[str, Any]] | None:
        """``--ckpt_path last``: the newest complete checkpoint under the run's folders, across its log versions.

        The folders: ``trainer.default_root_dir``, every logger's ``save_dir`` and every callback's ``dirpath``
        (:func:`~dapm_lightning.training.checkpointing.resolve_last_checkpoint`: a damaged ``last.ckpt`` is
        skipped with a warning). For ``fit``, with none there, ``"last"`` stays as it is (so that Lightning reads
        no SLURM ``hpc_ckpt`` either) and the run starts from scratch, saying so (the first submission of a job
        that is always launched with ``--ckpt_path last``); with only damaged ones, the run starts from scratch
        too. ``validate``, ``test`` and ``predict`` are refused instead
        (:class:`NoWeightsError`, naming the folders searched): they would run an untrained network.
        """
        roots, folders = cls._run_folders(config)
        training = subcommand not in EVALUATION_SUBCOMMANDS
        if not training and not cls._run_folders(config, current_directory=False)[0]:
            raise NoWeightsError(
                f"{subcommand} --ckpt_path last: the configuration names no run folder (trainer.default_root_dir, a "
                "logger's save_dir or a checkpoint callback's dirpath), so `last` would be the newest checkpoint of "
                f"any run under the current directory.\nFix: --trainer.default_root_dir set to the folder `fit` wrote "
                "its run to, or --ckpt_path CKPT naming a checkpoint file.")
        found = resolve_last_checkpoint(roots, folders, start_from_scratch=training)
        if found is None:
            damaged = find_last_checkpoint(roots) is not None
            if not training:
                where = ", ".join(dict.fromkeys(roots))
                what = ("none of the checkpoints there can be loaded (each named above)" if damaged
                        else "no last.ckpt there")
                raise NoWeightsError(
                    f"{subcommand} --ckpt_path last: looked for the run's newest checkpoint under {where}: {what}, so "
                    f"there are no trained weights to {subcommand} with.\nFix: --trainer.default_root_dir set to the "
                    "folder `fit` wrote its run to (as in the fit's config), or --ckpt_path CKPT naming a checkpoint "
                    "file (or a shipped model such as models/dapm-synthetic-r18-256).")
            if damaged:  # every checkpoint damaged (warned): from scratch, without
                config["ckpt_path"] = None  # Lightning's own lookup of "last" reading a damaged file
            else:  # Lightning's own note on it (quiet.FOREIGN_WARNINGS) suggests a setting the project has
                rank_zero_info(f"--ckpt_path last: no checkpoint of this run yet under "
                               f"{', '.join(map(str, dict.fromkeys(roots)))}: training starts from scratch")
            return None
        path, checkpoint = found
        rank_zero_info(f"--ckpt_path last: {'resuming from' if training else 'the weights of'} {path}")
        config["ckpt_path"] = str(path)
        return str(path), checkpoint


def _as_list(value: Any) -> list[Any]:
    return list(value) if isinstance(value, (list, tuple)) else [] if value in (None, False, True) else [value]


def run_lightning_cli(args: Sequence[str] | None = None, run: bool = True) -> DAPMCLI:
    """Parse ``args`` (``fit --config FILE ...``) and run the subcommand, without Lightning's tips."""
    quiet_lightning()
    return DAPMCLI(DAPMModule, DAPMDataModule, subclass_mode_data=True, seed_everything_default=0,
                   save_config_callback=SaveConfigOfRun, save_config_kwargs={"overwrite": True},
                   args=list(args) if args is not None else None, run=run, auto_configure_optimizers=False,
                   trainer_defaults=TRAINER_DEFAULTS)
