"""What the commands share (``train.py``, ``evaluate.py``, the sweep, the demo, dataset statistics,
labelling): a user's mistake (a bad value, a missing or foreign file, a folder that holds an
earlier run) is one line on stderr, ``error: <message>``, and exit status 1, not a traceback; and
under Hydra the output folder it made for the command is removed when the command failed with
nothing in it.
``HYDRA_FULL_ERROR=1`` shows the traceback as well.

    main = hydra_command("train", train)   # python train.py [key=value ...] runs main()
"""
from __future__ import annotations

import contextlib
import os
import re
import sys
import textwrap
import time
from pathlib import Path
from typing import Callable

from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import MissingMandatoryValue

from dagr_lite.config import CONF_DIR
from dagr_lite.errors import UserError

# What a user's mistake raises: UserError (ConfigError, ResumeError, DatasetFormatError, RecordingError,
# SensorError are UserErrors), OSError (a missing or foreign file, a folder that holds an earlier run,
# a full disk) and a mandatory config value left out. Any other exception is a bug: its traceback shows.
USER_ERRORS = (UserError, OSError, MissingMandatoryValue)
STARTED = time.time()  # when the command started (hydra_command's command() sets it), before Hydra made any folder
OMEGACONF_DETAIL = re.compile(r"\s+(full_key|object_type|reference_type)[:=]")


@contextlib.contextmanager
def user_errors():
    """Run a command's body; a user's mistake exits with one line (see the module notes)."""
    try:
        yield
    except USER_ERRORS as err:
        remove_empty_output_folder()
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        print(f"error: {user_message(err)}", file=sys.stderr, flush=True)
        raise SystemExit(1) from None
    except KeyboardInterrupt:  # Ctrl-C: what was finished stays; what was being written kept its partial name
        remove_empty_output_folder()
        print("interrupted", file=sys.stderr, flush=True)
        raise SystemExit(130) from None


def user_message(err: BaseException) -> str:
    """The error's message without omegaconf's detail lines (``full_key: ...``, ``object_type=...``);
    a missing mandatory value says how to give it."""
    message = "\n".join(without_detail(str(err)))
    missing = re.search(r"Missing mandatory value: ([\w.]+)", message)
    if missing:
        message += f"; give it on the command line: {missing.group(1)}=..."
    return message


def remove_empty_output_folder() -> None:
    """Remove the folder Hydra made for this command when it is empty, and, for a folder of the
    default layout ``runs/<kind>/<date>/<time>``, its parents up to ``runs`` that are then empty
    too. A folder with anything in it stays, and so does the current folder or one above it (detect's
    and the demo's Hydra folder is ``.``) and, for Hydra's own folder, an empty one last changed before
    the command started (a ``run_dir`` the user made and the command did not write into)."""
    try:
        from hydra.core.hydra_config import HydraConfig
        folder = Path(HydraConfig.get().runtime.output_dir).absolute()
    except (ImportError, ValueError):  # not run by Hydra
        return
    try:
        here = Path.cwd().resolve()
    except OSError:  # the current folder is gone: touch nothing
        return
    default = len(folder.parents) > 3 and folder.parents[2].name == "runs"
    for path in [folder, *(folder.parents[:3] if default else [])]:
        try:
            if path.resolve() == here or path.resolve() in here.parents or path.stat().st_mtime < STARTED - 1.0:
                break
            path.rmdir()  # only an empty folder
        except OSError:
            break


def hydra_command(config_name: str, run: Callable[[DictConfig], object]) -> Callable[[], None]:
    """A command's ``main``: Hydra composes ``conf/<config_name>.yaml`` with the command line and
    ``run(cfg)`` runs inside :func:`user_errors`. A command line that does not compose (a setting
    or an option that does not exist, an override that cannot be read) is one line too, before
    Hydra makes any folder (:func:`composition_problem`)."""
    import hydra

    @hydra.main(config_path=str(CONF_DIR), config_name=config_name, version_base=None)
    def main(cfg: DictConfig) -> None:
        with user_errors():
            run(cfg)
        remove_empty_output_folder()  # e.g. a resumed run that went on in its own folder

    def command() -> None:
        global STARTED
        STARTED = time.time()  # before Hydra makes any folder
        arguments = sys.argv[1:]
        helps = [a for a in arguments if a in ("--help", "-h")]
        if helps and not any(a.startswith("-") for a in arguments if a not in helps):  # else Hydra's flags and help
            with user_errors():
                print(command_help(config_name, [a for a in arguments if a not in helps]))
            return
        # Hydra's own flags (--cfg, --help, -m) and its settings (hydra.*) go to Hydra as they are.
        plain = not any(a.startswith("-") or a.lstrip("+~").startswith("hydra") for a in arguments)
        if plain and os.environ.get("HYDRA_FULL_ERROR") != "1":
            problem = composition_problem(config_name, arguments)
            if problem:
                print(f"error: {problem}", file=sys.stderr, flush=True)
                raise SystemExit(1)
        main()

    return command


def command_help(config_name: str, overrides: list[str]) -> str:
    """``--help``: the usage from ``conf/<config_name>.yaml``'s opening comments, the config groups
    that file composes with their options, and its settings composed with ``overrides`` (Hydra's own
    help would list every group of ``conf/``, those the command ignores too)."""
    problem = composition_problem(config_name, overrides)
    if problem:
        raise UserError(problem)
    text = (CONF_DIR / f"{config_name}.yaml").read_text()
    usage = []
    for line in text.splitlines():
        if not line.startswith("#"):
            break
        usage.append(line[1:].strip())
    lines = [*usage, "", "Config groups (group=option; conf/<group>/<option>.yaml):"]
    for group in composed_groups(text):
        options = sorted(path.stem for path in (CONF_DIR / group).glob("*.yaml"))
        lines.append(f"  {group}: {', '.join(options)}")
    from dagr_lite.config import compose_config
    cfg = compose_config(config_name, overrides, hydra=True)
    choices = {group: option for group, option in cfg.hydra.runtime.choices.items()
               if not group.startswith("hydra") and option is not None}
    with open_dict(cfg):
        del cfg["hydra"]
    descriptions = key_comments(config_files(config_name, choices))
    lines += ["", "Settings (key=value; `--cfg job` prints them, `--hydra-help` Hydra's flags):",
              with_comments(OmegaConf.to_yaml(cfg).rstrip(), descriptions)]
    return "\n".join(lines)


KEY_LINE = re.compile(r"^(\s*)([\w-]+):(?:\s+(.*?))?\s*$")


def config_files(config_name: str, choices: dict[str, str]) -> list[tuple[Path, str]]:
    """The files a command's settings come from, each with the key its settings lie under, in the
    order a key's meaning is looked up: the command's own file, then for each group the files its
    chosen option composes, the ones it starts from first (``model=events_only`` starts from
    ``hybrid``, a dataset's recipe from ``quick``), so an option's note on why it sets a key comes
    after what the key means. A file of ``# @package _global_`` lies at the top; a chosen option
    without a file (``optional recipe``) has none."""
    files = [(CONF_DIR / f"{config_name}.yaml", "")]
    for group, option in choices.items():
        for path in option_chain(CONF_DIR / group, option):
            head = path.read_text().split("\n", 1)[0]
            files.append((path, "" if head.strip() == "# @package _global_" else group))
    return files


def option_chain(folder: Path, option: str, seen: tuple[str, ...] = ()) -> list[Path]:
    """``folder/<option>.yaml`` after the options of its own group it starts from (its defaults
    list's plain entries, ``- hybrid``), theirs first; none when the file does not exist."""
    path = folder / f"{option}.yaml"
    if not path.is_file() or option in seen:
        return []
    bases = []
    for line in defaults_lines(path.read_text()):
        entry = re.match(r"\s*-\s*([\w-]+)\s*(?:#.*)?$", line)
        if entry and entry.group(1) != "_self_":
            bases += option_chain(folder, entry.group(1), (*seen, option))
    return [*bases, path]


def keyed_lines(lines: list[str]):
    """Each of a YAML text's ``lines`` with its key's dotted path from the top (``trainer.max_minutes``)
    and the part after its colon, or None and None for a line that sets no key (a comment, a list
    item, a blank line)."""
    stack: list[tuple[int, str]] = []  # (indent, key) of the lines the current one lies under
    for line in lines:
        match = KEY_LINE.match(line)
        if not match:
            yield line, None, None
            continue
        indent = len(match.group(1))
        while stack and stack[-1][0] >= indent:
            stack.pop()
        stack.append((indent, match.group(2)))
        yield line, ".".join(key for _, key in stack), match.group(3) or ""


def key_comments(files: list[tuple[Path, str]]) -> dict[str, str]:
    """``{dotted key: its comment}`` from config files, the first file to describe a key winning: a
    key's comment is the ``# ...`` after its value and the comment lines under it indented further."""
    comments: dict[str, str] = {}
    for path, package in files:
        current, indent = None, -1  # the key whose comment goes on, and its line's indent
        for line, key, value in keyed_lines(path.read_text().splitlines()):
            stripped = line.strip()
            if key is None:
                if stripped.startswith("#") and current is not None and len(line) - len(line.lstrip()) > indent:
                    comments[current] += " " + stripped.lstrip("#").strip()
                elif stripped.startswith("#") or not stripped:  # a header, a blank line: no comment goes on
                    current = None
                continue
            indent = len(line) - len(line.lstrip())
            current = f"{package}.{key}" if package else key
            comment = value.split(" #", 1)[1].strip() if " #" in value else value[1:].strip() if value.startswith("#") else ""
            if not comment or current in comments:
                current = None  # no comment here, or described before: its comment lines here are not carried on
            else:
                comments[current] = comment
    return comments


def with_comments(yaml_text: str, comments: dict[str, str], width: int = 110) -> str:
    """``yaml_text`` (as :func:`OmegaConf.to_yaml` writes it) with each key's comment after it,
    wrapped at ``width`` under its start."""
    out = []
    for line, key, _ in keyed_lines(yaml_text.splitlines()):
        comment = comments.get(key) if key is not None else None
        if not comment:
            out.append(line)
            continue
        column = max(len(line) + 2, 26)
        wrapped = textwrap.wrap(comment, max(width - column - 2, 40))
        out.append(f"{line:<{column}}# {wrapped[0]}")
        out.extend(f"{'':<{column}}# {part}" for part in wrapped[1:])
    return "\n".join(out)


def composed_groups(config_text: str) -> list[str]:
    """The config groups a command's config file composes: the entries of its defaults list
    (``- group: option``, ``- optional group: ...``), not ``_self_`` nor Hydra's own overrides."""
    groups = []
    for line in defaults_lines(config_text):
        entry = re.match(r"\s*-\s*(?:optional\s+)?([\w/]+)\s*:", line)
        if entry:  # `- override hydra/...: ...` does not match: a space before its colon
            groups.append(entry.group(1))
    return groups


def defaults_lines(config_text: str) -> list[str]:
    """The lines of a config file's defaults list (those after ``defaults:`` up to the next
    top-level key)."""
    lines, inside = [], False
    for line in config_text.splitlines():
        if line.startswith("defaults:"):
            inside = True
        elif inside and not line.startswith((" ", "\t")) and line.strip():
            break
        elif inside:
            lines.append(line)
    return lines


def composition_problem(config_name: str, overrides: list[str]) -> str | None:
    """Why ``conf/<config_name>.yaml`` does not compose with ``overrides``, in one line (None: it does)."""
    from hydra.errors import ConfigCompositionException, MissingConfigException, OverrideParseException

    from dagr_lite.config import compose_config
    try:
        compose_config(config_name, overrides)
    except MissingConfigException as err:  # a config group's option that does not exist
        text = str(err)
        missing = re.search(r"Could not find '([\w.]+)/([^']+)'", text)
        options = re.findall(r"^\t([\w.-]+)$", text, flags=re.MULTILINE)
        if missing and options:
            return (f"{missing.group(1)}={missing.group(2)}: no such option; {missing.group(1)} is one of "
                    f"{', '.join(options)}")
        return one_line(text)
    except ConfigCompositionException as err:
        ambiguous = re.search(r"Ambiguous value for argument '([^'=]+)=([^']*)'", str(err))
        if ambiguous:  # Hydra's advice includes --multirun, which no command here takes
            name, value = ambiguous.groups()
            return (f"{name}={value}: a list is written in brackets, {name}=[{value}] (a text with a comma: in "
                    f"quotes, {name}=\"'{value}'\")")
        key = re.search(r"Could not override '([^']+)'", str(err))
        if key and "No match in the defaults list" in str(err) and (CONF_DIR / key.group(1)).is_dir():
            # a config group that this command does not compose (Hydra's advice, '+group=', would add one)
            given = next((o for o in overrides if o.split("=", 1)[0] == key.group(1)), f"{key.group(1)}=...")
            source = "; the model comes from the checkpoint (ckpt=)" if key.group(1) == "model" else ""
            return f"{given}: conf/{config_name}.yaml takes no {key.group(1)} option{source}"
        if key and "not in struct" in str(err.__cause__ or ""):
            return (f"{key.group(1)}: no such setting in conf/{config_name}.yaml "
                    f"(`--cfg job` prints every setting)")
        return one_line(f"{err} ({err.__cause__})" if err.__cause__ else str(err))
    except OverrideParseException as err:
        return f"the command line cannot be read: {one_line(str(err))}"
    return added_setting_problem(config_name, overrides)


_ABSENT = object()  # OmegaConf.select's answer for a key that is not there


def added_setting_problem(config_name: str, overrides: list[str]) -> str | None:
    """Why an override that adds a key (Hydra's ``+key=value`` or ``++key=value``) would add one that no
    code reads (None: none does). A key may be added only to a collection of named entries (every
    value a mapping, as ``model.sizes``, to which a size of one's own can be added); a new key among
    settings is a misspelt one that Hydra would accept silently."""
    from dagr_lite.config import compose_config
    added = [o for o in overrides if o.startswith("+") and "=" in o]
    keys = [o.lstrip("+").split("=", 1)[0] for o in added]
    keys = [k for k in keys if "/" not in k and "@" not in k and not (CONF_DIR / k.replace(".", "/")).is_dir()]
    if not keys:  # none, or config groups' options (Hydra checks those)
        return None
    try:
        cfg = compose_config(config_name, [o for o in overrides if o not in added])
    except Exception:  # other overrides reach into what the '+' ones add: Hydra judges the whole line
        return None
    for key in keys:
        if OmegaConf.select(cfg, key, default=_ABSENT) is not _ABSENT:
            continue  # there already: `+` is Hydra's error to give, `++` sets it
        parent_key = key.rpartition(".")[0]
        parent = OmegaConf.select(cfg, parent_key, default=None) if parent_key else cfg
        entries = OmegaConf.to_container(parent, resolve=False) if isinstance(parent, DictConfig) else None
        named = bool(entries) and all(isinstance(value, dict) for value in entries.values())
        if not named:
            return (f"+{key}: no such setting in conf/{config_name}.yaml; a setting added with '+' would be read "
                    f"by nothing (`--cfg job` prints every setting)")
    return None


def without_detail(text: str) -> list[str]:
    """``text``'s lines without omegaconf's detail lines (``full_key: ...``, ``object_type=...``)."""
    return [line for line in text.splitlines() if not OMEGACONF_DETAIL.match(line)]


def one_line(text: str) -> str:
    """``text``'s lines, without omegaconf's detail lines and blank ones, joined by "; "."""
    return "; ".join(line.strip() for line in without_detail(text) if line.strip())
