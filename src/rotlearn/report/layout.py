"""A report's layout: a run's `report` node (an experiment's or a sweep's), checked.

`report_layout(node)` validates the node over `DEFAULT_REPORT` as a `ReportLayout` (pydantic)
and fills in each plot's file: `rotlearn.config` checks a run's node with it before the run
starts, `layout_of` a received run's before a report is written. Each plot is drawn into the
report's folder under a plain `.png` name. No pandas: validation imports it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Annotated, Any

from pydantic import AfterValidator, ConfigDict
from typing_extensions import TypedDict

from rotlearn import io
from rotlearn.errors import ConfigError, validation_words
from rotlearn.paths import OOD_EXAMPLES_FILE

__all__ = ["DEFAULT_REPORT", "OpenNode", "ReportLayout", "layout_of", "report_layout"]

DEFAULT_REPORT: dict[str, Any] = {
    "lead": "rep.name",
    "trial_keys": ["seed", "data.seed", "trial"],
    "plots": [{"kind": "curves"}],
}


def _png_name(name: str) -> str:
    """A plot's file: a plain name of a PNG file, written into the report's folder."""
    try:
        plain = io.plain_name(name).endswith(".png")
    except ValueError:
        plain = False
    if not plain:
        raise ValueError("should be a plain file name ending in .png (the plot is written into "
                         "the report's folder)")  # fmt: skip
    if name == OOD_EXAMPLES_FILE:  # a report into a run's own folder would replace it
        raise ValueError(f"should not be {OOD_EXAMPLES_FILE}, a run's own figure")
    return name


class OpenNode(TypedDict, total=False):
    """A node of the layout: the keys its subclass declares are checked; any other key is kept
    as it is (a later report may read it)."""

    __pydantic_config__ = ConfigDict(extra="allow")  # other keys are kept as they are


class PlotLayout(OpenNode, total=False):
    kind: str
    x: str
    label: str
    file: Annotated[str, AfterValidator(_png_name)]
    metrics: list[str]


class OODLayout(OpenNode, total=False):
    quantiles: list[float]
    sets: dict[str, Any]


class PaperLayout(OpenNode, total=False):
    where: dict[str, Any]
    rows: list[Any]


class ReportLayout(OpenNode, total=False):
    """A run's `report` node (`DEFAULT_REPORT` fills in what it leaves out)."""

    lead: str | None
    trial_keys: list[str] | None
    plots: list[PlotLayout] | None
    ood: OODLayout | None
    paper: PaperLayout | None


def report_layout(node: Mapping[str, Any]) -> dict[str, Any]:
    """The report layout of a `report` node: over `DEFAULT_REPORT`, validated as a
    `ReportLayout`, each plot's `file` filled in (`curves.png`, `<label>_box.png`).

    Raises:
        ConfigError: naming the key of a value that is not of its kind (`report.trial_keys`
            not a list of keys; `report.plots[0].file` no plain `.png` name, which could be
            written outside the report's folder).
    """
    from pydantic import TypeAdapter, ValidationError

    try:
        layout = TypeAdapter(ReportLayout).validate_python({**DEFAULT_REPORT, **node})
    except ValidationError as exc:
        error = exc.errors(include_url=False)[0]
        raise _refused(error["loc"], error["msg"], error["input"]) from None
    for i, plot in enumerate(layout.get("plots") or []):  # the file each plot is drawn into
        if plot.get("kind") == "curves":
            plot.setdefault("file", "curves.png")
        elif plot.get("kind") == "box" and not plot.get("file"):
            source = "label" if plot.get("label") else "x"
            try:
                name = str(plot.get(source, "")).split(".")[-1] if source == "x" else plot[source]
                plot["file"] = _png_name(f"{name}_box.png")
            except ValueError as exc:
                raise _refused(("plots", i, source), str(exc), plot.get(source)) from None
    layout["trial_keys"] = layout.get("trial_keys") or []
    return layout


def layout_of(configs: Sequence[Mapping[str, Any]], sources: Sequence[Any] | None = None) -> dict:
    """The report layout of runs: the first run's `report` node (`report_layout`).

    Args:
        configs: the runs' configs.
        sources: the file each config was read from (for messages).

    Raises:
        ValueError: '<config file>: report.<key>: ...' (`report_layout`).
    """
    sources = list(sources) if sources is not None else [None] * len(configs)
    node, where = next(((c["report"], s) for c, s in zip(configs, sources, strict=True)
                        if isinstance(c.get("report"), dict)), ({}, None))  # fmt: skip
    try:
        return report_layout(node)
    except ConfigError as exc:
        prefix = f"{where}: " if where is not None else ""
        raise ValueError(f"{prefix}{exc.key}: {exc.message}") from None


def _refused(loc: Sequence[Any], said: str, value: Any) -> ConfigError:
    """`report.<key>`: should be ..., got <value>' (pydantic's words, as `rotlearn.config`
    words them)."""
    key = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc)
    said = validation_words(said)
    shown = repr(value) if len(repr(value)) <= 80 else f"{repr(value)[:77]}..."
    return ConfigError(f"report{key}", f"{said}, got {shown}")
