"""Sphinx configuration of the bluesky-offsets documentation.

Build: ``sphinx-build -W --keep-going -b html docs docs/_build/html`` (``tests/test_docs.py`` runs
the same build and the pages' ``>>>`` examples).
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the packages as they are in this tree, also without `pip install -e`
os.environ.setdefault("MPLBACKEND", "Agg")

project = "bluesky-offsets"
author = "the bluesky-offsets authors"
copyright = "the bluesky-offsets authors, BSD-3-Clause"

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.intersphinx",
    "numpydoc",
    "sphinxarg.ext",
]

source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]
templates_path = ["_templates"]

# --- MyST: the Markdown pages as GitHub shows them ------------------------------------------------
myst_enable_extensions = ["colon_fence", "deflist"]
# `[text](page.md#a-heading)` links, as on GitHub (headings down to ###)
myst_heading_anchors = 3

# --- the API: one page per public module, found by walking the packages ---------------------------
autosummary_generate = True
autosummary_imported_members = False
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
# numpydoc: no per-class member tables (autodoc documents the members in place; the tables would
# ask for a stub page per method)
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False

# --- links to the projects we build on ------------------------------------------------------------
intersphinx_mapping = {
    "python": ("https://docs.python.org/3", None),
    "numpy": ("https://numpy.org/doc/stable", None),
    "bluesky": ("https://blueskyproject.io/bluesky/main", None),
    "ophyd-async": ("https://blueskyproject.io/ophyd-async/main", None),
    "tiled": ("https://blueskyproject.io/tiled", None),
}
intersphinx_timeout = 10  # offline, a silently dropped connection must not hold the build long

# Nothing is suppressed.  The one warning an offline build must survive, an intersphinx inventory
# that cannot be fetched, carries no warning type in Sphinx 9.0 (``sphinx/ext/intersphinx/_load.py``
# logs it untyped), so no ``suppress_warnings`` entry can name it alone: ``_OfflineInventories``
# below turns that one message into information.  Every other warning stays an error under -W.
suppress_warnings: list[str] = []

# --- HTML -----------------------------------------------------------------------------------------
html_theme = "pydata_sphinx_theme"
html_title = "bluesky-offsets"
html_static_path: list[str] = []
html_theme_options = {
    "navigation_with_keys": False,
    "show_toc_level": 2,
    "use_edit_page_button": False,
}
html_show_sourcelink = False


# --- offline builds -------------------------------------------------------------------------------
class _OfflineInventories(logging.Filter):
    """An intersphinx inventory that cannot be fetched (no network: here, and maybe in CI) is
    logged as information, not as a warning, so that ``-W`` builds pass offline; the links to
    those projects are then plain text.

    Only that one message is touched.  Sphinx 9.0 logs it (``sphinx/ext/intersphinx/_load.py``,
    "failed to reach any of the inventories with the following issues") with no warning type or
    subtype, so ``suppress_warnings`` cannot name it: a ``suppress_warnings`` entry for untyped
    warnings would silence every untyped warning.  Every other warning, from intersphinx or
    anywhere else, stays an error under ``-W``."""

    MESSAGE = "failed to reach any of the inventories"

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno == logging.WARNING and str(record.msg).startswith(self.MESSAGE):
            record.levelno, record.levelname = logging.INFO, "INFO"
            record.nonl = False  # a warning's record leaves the line's end to the warning stream
        return True


def _argparse_with_roles(app) -> None:
    """The sub-commands' descriptions are their modules' docstrings, with Sphinx roles in them
    (``:func:`plans.workflow.calibration_session```).  sphinx-argparse 0.6.1 parses a sub-command's
    description in a document of its own without the build's settings (``_print_subcommands``
    calls ``render_list(desc, markdown_help)``), and a role there fails with "'Values' object has
    no attribute 'env'"; here that document gets the build's environment, so the roles become
    links as anywhere else."""
    import sphinxarg.ext
    from docutils.frontend import get_default_settings
    from docutils.parsers.rst import Parser

    render_list = sphinxarg.ext.render_list

    def with_env(items, markdown_help, settings=None):
        if settings is None:
            settings = get_default_settings(Parser)
            settings.env = app.env
        return render_list(items, markdown_help, settings)

    sphinxarg.ext.render_list = with_env


def _numpydoc_template_once(app) -> None:
    """numpydoc (1.11) builds a Jinja environment and compiles its docstring template anew for every
    docstring it renders, twice per object (``mangle_docstrings``, ``mangle_signature``): some 3,000
    compilations here, 15 % of the build's CPU time.  The template is the same each time (numpydoc's
    own ``numpydoc_docstring.rst``, found as numpydoc finds it), so it is compiled once; should
    numpydoc's internals differ from what this expects, numpydoc is left as it is."""
    try:
        import numpydoc.docscrape_sphinx as scrape
        import numpydoc.numpydoc as numpydoc_ext
        from jinja2.sandbox import SandboxedEnvironment
        from sphinx.jinja2glue import BuiltinTemplateLoader

        loader = BuiltinTemplateLoader()
        loader.init(app.builder, dirs=[os.path.join(os.path.dirname(scrape.__file__), "templates")])
        template = SandboxedEnvironment(loader=loader).get_template("numpydoc_docstring.rst")
        parse, kinds = scrape.get_doc_object_orig, (scrape.SphinxClassDoc, scrape.SphinxFunctionDoc,
                                                    scrape.SphinxObjDoc)
        if numpydoc_ext.get_doc_object is not scrape.get_doc_object:
            return
    except (ImportError, AttributeError):
        return

    def get_doc_object(obj, what=None, doc=None, config=None, builder=None):
        config = {} if config is None else config
        config["template"] = template
        return parse(obj, what=what, doc=doc, config=config, class_doc=kinds[0], func_doc=kinds[1],
                     obj_doc=kinds[2])

    numpydoc_ext.get_doc_object = get_doc_object


def setup(app):
    # sphinx.util.logging.getLogger("sphinx.ext.intersphinx") is Python's "sphinx.sphinx.ext.intersphinx"
    logging.getLogger("sphinx.sphinx.ext.intersphinx").addFilter(_OfflineInventories())
    _argparse_with_roles(app)
    app.connect("builder-inited", _numpydoc_template_once)
