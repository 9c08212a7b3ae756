"""ROS 2 ``.msg`` definitions of the Jazzy types, written out for zenoh-ros2-sdk.

zenoh-ros2-sdk computes RIHS01 hashes and registers types from ``.msg`` text (it would
download the definitions from GitHub, which the tests cannot reach). The text is rendered
here from the field definitions of ``rosbags``' Jazzy type store (field names and types
only: the five types and their dependencies have no default values, and constants do not
enter a type hash); the SDK then parses it and hashes it with its own code.
"""

from __future__ import annotations

from pathlib import Path

from rosbags.typesys import Stores, get_typestore

_STORE = get_typestore(Stores.ROS2_JAZZY)


def _short(name: str) -> str:
    pkg, _, typ = name.split("/")
    return f"{pkg}/{typ}"


def _field_type(node: tuple) -> tuple[str, list[str]]:
    kind, detail = node
    kind = int(kind)
    if kind == 1:  # base type: (name, string bound)
        base, bound = detail
        return (f"{base}<={bound}" if bound else base), []
    if kind == 2:  # nested message
        return _short(detail), [detail]
    inner, size = detail
    text, deps = _field_type(inner)
    if kind == 3:  # fixed array
        return f"{text}[{size}]", deps
    return (f"{text}[<={size}]" if size else f"{text}[]"), deps  # sequence


def msg_text(ros_type: str) -> str:
    """The ``.msg`` text of ``ros_type`` (one ``type name`` line per field)."""
    _consts, fields = _STORE.fielddefs[ros_type]
    return "".join(f"{_field_type(node)[0]} {name}\n" for name, node in fields)


def dependencies(ros_type: str) -> dict[str, str]:
    """``{type: .msg text}`` of every type ``ros_type`` refers to, recursively."""
    out: dict[str, str] = {}
    todo = [ros_type]
    while todo:
        t = todo.pop()
        for _name, node in _STORE.fielddefs[t][1]:
            for dep in _field_type(node)[1]:
                if dep not in out:
                    out[dep] = msg_text(dep)
                    todo.append(dep)
    return out


def write_messages_dir(root: Path, types: list[str]) -> Path:
    """Write ``<root>/<pkg>/msg/<Name>.msg`` for ``types`` and their dependencies."""
    every = {t: msg_text(t) for t in types}
    for t in types:
        every.update(dependencies(t))
    for t, text in every.items():
        pkg, _, name = t.split("/")
        path = root / pkg / "msg" / f"{name}.msg"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    return root
