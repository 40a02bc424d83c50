"""YAML with positions: plain Python values plus the line/column of every key and value.

``load_with_marks(text, filename)`` returns a ``MarkedDoc``: the parsed data (dicts,
lists, scalars) and a table ``path -> (line, column)`` (1-based) so that any error
about ``motors.in.rated_current_a`` can say ``profiles/cvt.yaml:23:5``.

Differences from ``yaml.safe_load``, on purpose:
- ``1e-5`` is a float (YAML 1.1 wants ``1.0e-5``; a profile author should not care);
- duplicate keys are an error (PyYAML silently keeps the last one);
- keys must be text; recursive aliases are refused.
"""
from __future__ import annotations

import difflib
import re
from dataclasses import dataclass, field

import yaml

from ..errors import ProfileError

Path_ = tuple  # a location inside the document: ("motors", "in", "kt_datasheet") or ("steps", 2)


class _Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # libyaml's parser is ~10x faster
    """SafeLoader whose float resolver also accepts ``1e-5`` and ``3E2``."""


# Copy the resolver table so the change stays local to this loader.
_Loader.yaml_implicit_resolvers = {k: list(v) for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                    |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                    |[-+]?\.(?:inf|Inf|INF)
                    |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."))


_PLAIN_KEY = re.compile(r"[^\s.\[\]'\"]{1,40}")


def format_path(path: Path_) -> str:
    """``("steps", 2, "motor")`` -> ``steps[2].motor``; odd keys are quoted: ``motors['a b']``."""
    out = ""
    for part in path:
        if isinstance(part, int):
            out += f"[{part}]"
        elif _PLAIN_KEY.fullmatch(part):
            out += ("." if out else "") + part
        else:
            out += f"[{one_line(repr(part[:40]))}]"
    return out or "<document>"


def one_line(text: str) -> str:
    """Messages are one line: escape line breaks and other control characters."""
    return "".join(ch if ch.isprintable() else repr(ch)[1:-1] for ch in text)


@dataclass
class MarkedDoc:
    """Parsed YAML data plus where each key and value sits in the file."""

    filename: str
    data: object
    key_marks: dict = field(default_factory=dict)     # path -> (line, col) of the key
    value_marks: dict = field(default_factory=dict)   # path -> (line, col) of the value

    def where(self, path: Path_) -> tuple[int, int]:
        """Best position for ``path``: its key, else its value, else the nearest parent."""
        path = tuple(path)
        while True:
            if path in self.key_marks:
                return self.key_marks[path]
            if path in self.value_marks:
                return self.value_marks[path]
            if not path:
                return (1, 1)
            path = path[:-1]

    def value_where(self, path: Path_) -> tuple[int, int]:
        path = tuple(path)
        return self.value_marks.get(path) or self.where(path)

    def error(self, path: Path_, problem: str, fix: str = "", *, at_value: bool = False) -> ProfileError:
        """A ``ProfileError`` reading ``file:line:col: path: problem; fix``."""
        line, col = self.value_where(path) if at_value else self.where(path)
        msg = f"{self.filename}:{line}:{col}: {format_path(path)}: {problem}"
        if fix:
            msg += f"; {fix}"
        return ProfileError(one_line(msg))


def did_you_mean(word: str, choices) -> str:
    """``"did you mean 'rated_current_a'?"`` or a list of the allowed words."""
    choices = sorted(str(c) for c in choices)
    close = difflib.get_close_matches(str(word)[:80], choices, n=1, cutoff=0.6)
    if close:
        return f"did you mean '{close[0]}'?"
    return "allowed: " + ", ".join(choices) if choices else "remove it"


_MAX_DEPTH = 50


def load_with_marks(text: str, filename: str) -> MarkedDoc:
    """Parse ``text``; YAML syntax errors become a ``ProfileError`` with line and column."""
    loader = _Loader(text)
    try:
        try:
            root = loader.get_single_node()
        finally:
            loader.dispose()
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line, col = (mark.line + 1, mark.column + 1) if mark else (1, 1)
        problem = one_line(exc.problem or exc.context or "invalid YAML")
        raise ProfileError(f"{filename}:{line}:{col}: YAML syntax error: {problem}; "
                           f"fix the indentation/quoting at that position") from None
    except RecursionError:
        raise ProfileError(f"{filename}:1:1: YAML nested too deeply; flatten the profile") from None
    except yaml.YAMLError as exc:  # e.g. reader errors (control characters)
        raise ProfileError(f"{filename}:1:1: unreadable YAML: {one_line(str(exc).splitlines()[0])}; "
                           f"save the profile as plain UTF-8 text") from None
    doc = MarkedDoc(filename, None)
    if root is None:
        return doc
    try:
        doc.data = _convert(loader, root, (), doc, set())
    except RecursionError:
        raise ProfileError(f"{filename}:1:1: YAML nested too deeply; flatten the profile") from None
    return doc


def _mark(node) -> tuple[int, int]:
    return (node.start_mark.line + 1, node.start_mark.column + 1)


def _convert(loader: _Loader, node, path: Path_, doc: MarkedDoc, active: set):
    doc.value_marks.setdefault(path, _mark(node))
    if id(node) in active or len(path) > _MAX_DEPTH:
        raise doc.error(path, "recursive alias or nesting too deep", "remove the self-referencing '*alias'",
                        at_value=True)
    if isinstance(node, yaml.ScalarNode):
        try:
            return loader.construct_object(node, deep=True)
        except (yaml.YAMLError, ValueError, TypeError, OverflowError) as exc:
            raise doc.error(path, f"unreadable value ({str(exc).splitlines()[0]})",
                            "quote it or write a plain number", at_value=True) from None
    active = active | {id(node)}
    if isinstance(node, yaml.SequenceNode):
        return [_convert(loader, item, path + (i,), doc, active) for i, item in enumerate(node.value)]
    if isinstance(node, yaml.MappingNode):
        try:
            loader.flatten_mapping(node)  # resolves '<<: *anchor' merge keys
        except yaml.YAMLError as exc:
            raise doc.error(path, f"bad merge key ({getattr(exc, 'problem', exc)})",
                            "merge only mappings with '<<: *anchor'", at_value=True) from None
        out: dict = {}
        for key_node, value_node in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                raise doc.error(path, f"a key at line {_mark(key_node)[0]} is not plain text",
                                "write keys as plain words", at_value=True)
            try:
                key = loader.construct_object(key_node, deep=True)
            except (yaml.YAMLError, ValueError, TypeError, OverflowError):
                key = None
            if not isinstance(key, str):
                line, col = _mark(key_node)
                raise ProfileError(one_line(f"{doc.filename}:{line}:{col}: {format_path(path)}: key "
                                            f"'{key_node.value}' is not text (YAML reads it as "
                                            f"{type(key).__name__}); quote it, e.g. \"{key_node.value}\":"))
            if key in out:
                line, col = _mark(key_node)
                raise ProfileError(one_line(f"{doc.filename}:{line}:{col}: {format_path(path + (key,))}: "
                                            f"duplicate key; keep only one '{key}:'"))
            doc.key_marks[path + (key,)] = _mark(key_node)
            out[key] = _convert(loader, value_node, path + (key,), doc, active)
        return out
    raise doc.error(path, "unsupported YAML node", "use mappings, lists and plain values", at_value=True)
