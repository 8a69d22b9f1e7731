"""Sphinx configuration of rotlearn's documentation site (`make docs`; docs/_build/html)."""

import importlib.util
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))  # document these sources, whatever is installed

import rotlearn  # noqa: E402

project = "rotlearn"
author = "rotlearn developers"
copyright = "the rotlearn developers"
version = release = rotlearn.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",  # the docstrings are Google style (Args:, Returns:, Raises:)
    "sphinx.ext.viewcode",
    "myst_parser",  # the Markdown pages (architecture, results, conventions)
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build"]
if importlib.util.find_spec("rotlearn.nn") is None:  # the drop-in layers are not in this tree yet
    exclude_patterns.append("api/nn.rst")

# `name` in a docstring is a cross-reference when it names something documented, else code;
# `.hydra/config.yaml` or `.npy` is a file name, shown with its dot (`_code_or_xref`).
default_role = "code-or-xref"
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_inherit_docstrings = False  # not Lightning's docstrings of the hooks rotlearn overrides
autodoc_typehints = "description"
autodoc_typehints_description_target = "documented_params"  # not a base's *args, **kwargs
autodoc_class_signature = "mixed"  # class Name(arg=default, ...): how a reader calls it
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
napoleon_custom_sections = [("Return values", "params_style")]  # see _named_returns
napoleon_use_ivar = True  # "Attributes:" as fields, not a second description of each member

myst_enable_extensions = ["dollarmath"]
myst_heading_anchors = 3

html_theme = "furo"
html_title = f"rotlearn {release}"

# The docstrings are plain text with `code` spans (they read well in a terminal and in `help()`),
# and their formulas use | and * as in |q| and a * b. reStructuredText would read those as
# substitutions and emphasis, so outside code spans they are escaped before napoleon runs.
_CODE = re.compile(r"(``.+?``|`[^`]+`)", re.S)
_NAMED = re.compile(r"\s*[A-Za-z_]\w*: ")
_SECTION = re.compile(r"(Args|Arguments|Returns|Raises|Yields|Attributes|Examples?|Notes?):$")


def _escape(text: str) -> str:
    text = re.sub(r"(?<!\\)([|*])", r"\\\1", text)
    text = re.sub(r"(?m)^(\s*)\\\* ", r"\1* ", text)  # keep "* " bullets
    return re.sub(r"(?<=\w)_(?!\w)", r"\\_", text)  # err_ is text, not a link target


def _named_returns(lines: list[str]) -> None:
    """A Returns: section that names several results ("q: (..., 4) ...") reads as a list of
    them, as Args: does (napoleon would take the first name for a type); one that names none
    reads as written, colons and all."""
    for start, line in enumerate(lines):
        if line.strip() != "Returns:":
            continue
        indent = len(line) - len(line.lstrip())
        body = []
        for entry in lines[start + 1 :]:
            if entry.strip() and len(entry) - len(entry.lstrip()) <= indent:
                break
            body.append(entry)
        items = [e for e in body if e.strip()]
        if not items:
            continue
        step = min(len(e) - len(e.lstrip()) for e in items)
        named = [e for e in items if len(e) - len(e.lstrip()) == step and _NAMED.match(e)]
        if len(named) >= 2:
            lines[start] = line.replace("Returns:", "Return values:")
        elif not _NAMED.match(items[0]) and ":" in _CODE.sub("", items[0]):
            # "(...,) degrees in [0, 180]: the angle": napoleon reads the text before the first
            # colon as the type; an empty one before it keeps the whole line the description
            at = lines.index(items[0], start)
            lines[at] = f"{' ' * step}: {items[0].lstrip()}"


def _plain_text_docstring(app, what, name, obj, options, lines) -> None:
    # `"""Args:` on the docstring's first line leaves its entries unindented: indent them.
    if len(lines) > 1 and _SECTION.match(lines[0].strip()) and lines[1][:1].strip():
        lines[1:] = [f"    {line}" if line else line for line in lines[1:]]
    _named_returns(lines)
    parts = _CODE.split("\n".join(lines))
    for i in range(1, len(parts), 2):  # `x`(lam), `nn.Module`s: a code span glued to a word
        if parts[i - 1][-1:].isalnum():
            parts[i - 1] += "\\ "
        if parts[i + 1][:1].isalnum() or parts[i + 1][:1] == "(":
            parts[i + 1] = "\\ " + parts[i + 1]
    text = "".join(part if i % 2 else _escape(part) for i, part in enumerate(parts))
    lines[:] = text.split("\n")


def command_help(command: str) -> str:
    """What `<command> --help` prints (the argparse commands; rotlearn-train's own usage)."""
    import contextlib
    import importlib
    import io

    if command in ("rotlearn-train", "rotlearn-eval"):
        from rotlearn.cli import evaluate, train
        from rotlearn.paths import config_dir

        usage = train.usage if command == "rotlearn-train" else evaluate.usage
        return usage().replace(str(config_dir()), "conf")  # not the building machine's path
    module = {"rotlearn-predict": "predict", "rotlearn-report": "report",
              "rotlearn-make-demo-data": "make_demo_data"}[command]  # fmt: skip
    main = importlib.import_module(f"rotlearn.cli.{module}").main
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
        main(["--help"])
    return out.getvalue()


def _command_help_directive():
    from docutils import nodes
    from sphinx.util.docutils import SphinxDirective

    class CommandHelp(SphinxDirective):
        """`{command-help} <command>`: the command's --help, as a literal block."""

        required_arguments = 1

        def run(self):
            text = command_help(self.arguments[0]).rstrip()
            block = nodes.literal_block(text, text)
            block["language"] = "text"
            return [block]

    return CommandHelp


def _code_or_xref(name, rawtext, text, lineno, inliner, options=None, content=None):
    """The docstrings' default role: Python's `obj` role, except for text that starts with a dot,
    which is a file or folder name (`.hydra/config.yaml`, `.npy`), and text with a placeholder
    (`<out>/<name>`, `rotlearn.data.<name>`), both shown as written (the Python role reads a
    leading dot as "search relatively" and `title <target>` as a link, dropping `<name>`)."""
    from docutils import nodes

    if text.startswith(".") or "<" in text:
        return [nodes.literal(rawtext, text)], []
    role = inliner.document.settings.env.get_domain("py").role("obj")
    return role(name, rawtext, text, lineno, inliner, options or {}, content or [])


def _own_signature(app, what, name, obj, options, signature, return_annotation):
    """A class that takes no argument of its own (a layer on `torch.nn.Module`'s `__init__`)
    shows `()`, not the base's `(*args, **kwargs)`."""
    own = any("__init__" in vars(c) for c in getattr(obj, "__mro__", ())
              if c.__module__.startswith("rotlearn"))  # fmt: skip
    if what == "class" and signature == "(*args, **kwargs)" and not own:
        return "()", return_annotation
    return None


_DOTTED = re.compile(r"rotlearn(\.\w+)*")


def _link_api_names(app, doctree, docname) -> None:
    """On the Markdown pages, a code span that is a documented name (`rotlearn.nn.ALayer`,
    `rotlearn.bingham`) links to its API entry, as the docstrings' names do."""
    from docutils import nodes

    if app.env.doc2path(docname).suffix != ".md":
        return
    domain = app.env.get_domain("py")
    for literal in list(doctree.findall(nodes.literal)):
        name = literal.astext().removesuffix("()")
        if isinstance(literal.parent, nodes.reference) or not _DOTTED.fullmatch(name):
            continue
        found = domain.objects.get(name)
        if found is None:
            continue
        uri = app.builder.get_relative_uri(docname, found.docname) + "#" + found.node_id
        literal.replace_self(nodes.reference("", "", literal.deepcopy(), refuri=uri,
                                             internal=True))  # fmt: skip


def setup(app) -> None:
    app.connect("doctree-resolved", _link_api_names)
    app.add_role("code-or-xref", _code_or_xref)
    app.connect("autodoc-process-signature", _own_signature)
    app.connect("autodoc-process-docstring", _plain_text_docstring, priority=400)  # before napoleon
    app.add_directive("command-help", _command_help_directive())
