"""A stand-in for ``bpy.types.UILayout`` that records what a ``draw()`` puts on screen.

Nothing can be drawn in module mode (no GPU context), so panels are tested by running their real
``draw`` against this recorder. Every call is checked against Blender's own RNA description of
``UILayout``: the function must exist, its keyword names must be real parameters, icons must be
real icon names, ``prop`` must name a real property of its data, ``operator`` a registered
operator, and values assigned to the returned operator properties must be its real properties.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import bpy

_FUNCS = bpy.types.UILayout.bl_rna.functions
_LAYOUT_PROPS = set(bpy.types.UILayout.bl_rna.properties.keys())
_ICONS = set(_FUNCS["label"].parameters["icon"].enum_items.keys())
_CONTAINERS = ("row", "column", "box", "split", "grid_flow", "column_flow")


@dataclass
class Item:
    kind: str  # label, prop, operator, progress, separator
    args: dict
    enabled: bool
    alert: bool
    op_props: dict = field(default_factory=dict)

    @property
    def text(self) -> str:
        return str(self.args.get("text", ""))


class _OperatorProps:
    """What ``layout.operator()`` returns: assignments checked against the operator's RNA."""

    def __init__(self, idname: str, store: dict):
        category, name = idname.split(".")
        rna = getattr(getattr(bpy.ops, category), name).get_rna_type()
        object.__setattr__(self, "_names", set(rna.properties.keys()))
        object.__setattr__(self, "_store", store)

    def __setattr__(self, name, value):
        assert name in self._names, f"operator has no property {name!r}"
        self._store[name] = value


class RecordingLayout:
    def __init__(self, parent: RecordingLayout | None = None, items: list | None = None):
        object.__setattr__(self, "_parent", parent)
        object.__setattr__(self, "items", items if items is not None else [])
        object.__setattr__(self, "_attrs", {"enabled": True, "alert": False, "active": True})

    # -- attributes such as enabled, alert, scale_y ----------------------------------------
    def __setattr__(self, name, value):
        assert name in _LAYOUT_PROPS, f"UILayout has no attribute {name!r}"
        self._attrs[name] = value

    def __getattr__(self, name):
        if name in _LAYOUT_PROPS:
            return self._attrs.get(name)
        raise AttributeError(name)

    def _effective(self, name: str) -> bool:
        node, values = self, []
        while node is not None:
            values.append(node._attrs.get(name))
            node = node._parent
        if name == "alert":
            return any(bool(v) for v in values)
        return all(v is not False for v in values)

    # -- calls ----------------------------------------------------------------------------
    def _check(self, func: str, args: tuple, kwargs: dict) -> dict:
        assert func in _FUNCS, f"UILayout has no function {func!r}"
        params = [p.identifier for p in _FUNCS[func].parameters]
        named = dict(zip(params, args, strict=False))
        for key in kwargs:
            assert key in params, f"UILayout.{func}() has no parameter {key!r}"
        named.update(kwargs)
        icon = named.get("icon")
        if icon is not None:
            assert icon in _ICONS, f"unknown icon {icon!r}"
        return named

    def _container(self, func, args, kwargs):
        self._check(func, args, kwargs)
        return RecordingLayout(self, self.items)

    def _record(self, kind, named, op_props=None):
        item = Item(kind, named, self._effective("enabled"), self._effective("alert"),
                    op_props if op_props is not None else {})
        self.items.append(item)
        return item

    def label(self, *args, **kwargs):
        self._record("label", self._check("label", args, kwargs))

    def separator(self, *args, **kwargs):
        self._record("separator", self._check("separator", args, kwargs))

    def progress(self, *args, **kwargs):
        named = self._check("progress", args, kwargs)
        assert 0.0 <= named.get("factor", 0.0) <= 1.0
        self._record("progress", named)

    def prop(self, *args, **kwargs):
        named = self._check("prop", args, kwargs)
        data, prop = named["data"], named["property"]
        assert prop in data.bl_rna.properties, f"{data!r} has no property {prop!r}"
        self._record("prop", named)

    def menu(self, *args, **kwargs):
        named = self._check("menu", args, kwargs)
        assert isinstance(getattr(bpy.types, named["menu"], None), type), f"no menu {named['menu']}"
        self._record("menu", named)

    def operator(self, *args, **kwargs):
        named = self._check("operator", args, kwargs)
        idname = named["operator"]
        category, name = idname.split(".")
        assert hasattr(bpy.types, f"{category.upper()}_OT_{name}"), f"no operator {idname}"
        store: dict = {}
        self._record("operator", named, store)
        return _OperatorProps(idname, store)

    def __getattribute__(self, name):
        if name in _CONTAINERS:
            return lambda *a, **k: self._container(name, a, k)
        return object.__getattribute__(self, name)

    # -- queries for tests ------------------------------------------------------------------
    def texts(self) -> list[str]:
        return [i.text for i in self.items if i.kind in ("label", "progress")]

    def joined(self) -> str:
        """All label text, with wrapped lines joined back together."""
        return " ".join(self.texts())

    def operators(self, idname: str | None = None) -> list[Item]:
        ops = [i for i in self.items if i.kind == "operator"]
        return [i for i in ops if idname is None or i.args["operator"] == idname]

    def props(self) -> list[str]:
        return [i.args["property"] for i in self.items if i.kind == "prop"]

    def alerts(self) -> list[str]:
        return [i.text for i in self.items if i.kind == "label" and i.alert]
