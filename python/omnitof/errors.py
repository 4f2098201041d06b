"""Exceptions of omnitof.

Library code raises these; the command line turns them into one clear line and a non-zero exit
status, never a traceback, because they describe a user's mistake (bad file, bad value), not a bug.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml


class OmnitofError(Exception):
    """Base class of every error omnitof raises on purpose."""


class InputError(OmnitofError):
    """Bad input data: names the file and, where known, the line and what was expected."""

    def __init__(self, message: str, path: str | Path | None = None, line: int | None = None):
        self.path = None if path is None else Path(path)
        self.line = line
        self.reason = message
        where = ""
        if path is not None:
            where = f"{path}" + (f":{line}" if line is not None else "") + ": "
        super().__init__(where + message)


class ConfigError(OmnitofError):
    """An invalid configuration value; the message names the field."""


class OutputError(OmnitofError):
    """An output that cannot be written where asked: a file where a folder should be, a folder
    that cannot be created or written, a full disk. The message names the path."""


class ResourceError(OmnitofError):
    """A run that would need more than the machine has (memory); the message names the number
    and the setting that decides it."""


class OmnitofWarning(UserWarning):
    """Something in the user's data was accepted but deserves a look; the command line prints
    it as one line (`omnitof: warning: ...`). Each reader has its own subclass."""


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping: PyYAML keeps the last
    silently, so `particles: 30` above `particles: 3` would run with 3 and no word said."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *base` may override on purpose
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                duplicate = key in seen
                seen.add(key)
            except TypeError:  # an unhashable key; PyYAML's own check reports it
                continue
            if duplicate:
                raise yaml.constructor.ConstructorError(
                    None, None, f"the key {str(key)[:40]!r} is given twice in one mapping", key_node.start_mark
                )
        return super().construct_mapping(node, deep=deep)


_INT, _FLOAT = "tag:yaml.org,2002:int", "tag:yaml.org,2002:float"


def _numbers_without_base_60(cls: type, keep_yaml_1_1: bool = False) -> None:
    """Numbers in `cls` (a loader or a dumper) as PyYAML's YAML 1.1 reads them, less base 60
    and plus exponents without a dot: `10:00` was the integer 600 (`--set filter.particles=10:00`
    ran 600 particles) and `5e-2` a string (ROS map files write resolutions so); both as YAML
    1.2 reads them. Every other implicit type (bool, null, octal 010, 1_000, timestamps) stays as
    PyYAML has it. A dumper keeps YAML 1.1's rules as well (`keep_yaml_1_1`), so that it quotes
    every string that either would read as a number: what it writes reads back the same here
    and in other YAML 1.1 tools."""
    cls.yaml_implicit_resolvers = {
        first: [(tag, regexp) for tag, regexp in entries if keep_yaml_1_1 or tag not in (_INT, _FLOAT)]
        for first, entries in yaml.SafeLoader.yaml_implicit_resolvers.items()
    }
    cls.add_implicit_resolver(
        _INT, re.compile(r"^(?:[-+]?0b[0-1_]+|[-+]?0[0-7_]+|[-+]?(?:0|[1-9][0-9_]*)|[-+]?0x[0-9a-fA-F_]+)$"),
        list("-+0123456789"),
    )
    cls.add_implicit_resolver(
        _FLOAT, re.compile(r"^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?|[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+"
                           r"|[-+]?\.[0-9][0-9_]*(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"),
        list("-+0123456789."),
    )


def displayable(text: str) -> str:
    """`text` with every byte that was not UTF-8 shown as an escape: a file name that is not valid
    UTF-8 reaches Python with surrogate escapes (PEP 383: a Latin-1 "café.clf" is "caf\\udce9.clf"),
    which neither UTF-8 files nor fonts take; it becomes "caf\\xe9.clf"."""
    return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


class YamlDumper(getattr(yaml, "CSafeDumper", yaml.SafeDumper)):  # type: ignore[misc]
    """PyYAML's safe dumper (the C one where built) with `load_yaml`'s numbers: every YAML the
    project writes is read back by `load_yaml` to what was written (bar the bytes of a file name
    that is not UTF-8, which it writes as `displayable` shows them)."""


def _represent_text(dumper: yaml.BaseDumper, text: str) -> yaml.Node:
    return dumper.represent_str(displayable(text))


_numbers_without_base_60(_UniqueKeyLoader)
_numbers_without_base_60(YamlDumper, keep_yaml_1_1=True)
YamlDumper.add_representer(str, _represent_text)


def dump_yaml(data: Any, stream: Any = None, **options: Any) -> Any:
    """`yaml.safe_dump` with `YamlDumper` (the text, or None when written to `stream`); other
    alphabets than Latin written as they are (a user's file names), not as escapes, and a long
    text (a path under a deep folder) on one line, which PyYAML folds at 80 characters: a user
    searching summary.yaml for their file's path finds it."""
    options.setdefault("allow_unicode", True)
    options.setdefault("width", 1 << 16)
    return yaml.dump(data, stream, Dumper=YamlDumper, **options)


def load_yaml(text: str) -> Any:
    """`yaml.safe_load`, where everything a hostile or mistyped text makes PyYAML raise is a
    `yaml.YAMLError` (for `yaml_problem`): besides its own errors, a ValueError from a value it
    cannot convert (an integer of more than 4300 digits, a date such as 2024-13-45) and a
    RecursionError from nesting deeper than Python's stack allows. A key given twice in one
    mapping is an error too."""
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader)
    except RecursionError:
        raise yaml.YAMLError("nested too deeply to read") from None
    except ValueError as err:
        raise yaml.YAMLError(f"a value that cannot be read ({' '.join(str(err).split(';')[0].split())})") from None


def read_yaml_mapping(path: Any, what: str, not_a_mapping: str) -> dict[str, Any]:
    """The YAML file at `path`, which must hold a mapping; else one InputError naming it: a file
    that cannot be read ("cannot read `what`: ..."), not YAML (with its line), or holding
    something else (`not_a_mapping`, ", got list")."""
    from pathlib import Path

    path = Path(path)
    try:
        data = load_yaml(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"cannot read {what}: {read_problem(err)}", path) from None
    except yaml.YAMLError as err:
        problem, line = yaml_problem(err)
        raise InputError(problem, path, line) from None
    if not isinstance(data, dict):
        raise InputError(f"{not_a_mapping}, got {type(data).__name__}", path)
    return data


def yaml_problem(err: Exception) -> tuple[str, int | None]:
    """What a YAML parser found wrong, on one line ("not valid YAML: ..."), and the 1-based line
    of the file where it found it (None where the parser does not say): PyYAML's own message
    spans several lines and quotes the text."""
    mark = getattr(err, "problem_mark", None)
    problem = getattr(err, "problem", None) or " ".join(str(err).split())
    return f"not valid YAML: {problem}", None if mark is None else mark.line + 1


def leading_problem(problems: list[dict[str, Any]]) -> dict[str, Any]:
    """The one of pydantic's validation problems (`ValidationError.errors()`) to report first: an
    unknown field where there is one, since a misspelt field is also why the field meant is
    "required" (an experiment's `inputz:` read "inputs: Field required")."""
    return next((p for p in problems if p.get("type") == "extra_forbidden"), problems[0])


def read_problem(err: OSError | UnicodeDecodeError | ValueError) -> str:
    """What went wrong reading a file, for a message that already names it: OSError's own text
    repeats the path ("[Errno 36] File name too long: '/a/...'"), after the path was named."""
    if isinstance(err, UnicodeDecodeError):
        return f"not UTF-8 text (byte {err.start})"
    if isinstance(err, OSError) and err.strerror:
        return err.strerror
    return str(err)


def os_error_message(err: OSError) -> str:
    """An OSError that reached the command line, path first as in every other message."""
    if err.filename is None or not err.strerror:
        return str(err)
    target = f" -> {err.filename2}" if err.filename2 is not None else ""
    return f"{err.filename}{target}: {err.strerror}"
