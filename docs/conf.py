"""Sphinx configuration: myst for the Markdown pages, numpydoc for the API, autosummary
for one page per public name, sphinx-gallery for the examples (not executed here: the
figures are the ones the examples save, shown on their pages)."""

from importlib.metadata import version as _version

project = "latentsindy"
author = "the latentsindy developers"
copyright = "2026, the latentsindy developers"  # noqa: A001
release = _version("latentsindy")
version = ".".join(release.split(".")[:2])

extensions = [
    "myst_parser",
    "numpydoc",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.intersphinx",
    "sphinx.ext.mathjax",
    "sphinx_gallery.gen_gallery",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "generated_gallery/*.ipynb", "**/*.codeobj.json"]
myst_heading_anchors = 3
suppress_warnings = ["myst.header", "config.cache"]

autosummary_generate = True
autosummary_imported_members = True
autodoc_default_options = {"members": True, "inherited-members": False}
autodoc_typehints = "none"
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_validation_checks = set()
numpydoc_xref_param_type = False

sphinx_gallery_conf = {
    "examples_dirs": "../examples",
    "gallery_dirs": "generated_gallery",
    "plot_gallery": "False",  # CI never runs the examples here; the tests run them
    "download_all_examples": False,
    "filename_pattern": r"^$",
    "ignore_pattern": r"__init__\.py",
}

intersphinx_mapping = {}
html_theme = "pydata_sphinx_theme"
html_title = f"latentsindy {release}"
html_theme_options = {"navigation_with_keys": False, "show_toc_level": 2}
html_static_path = []
templates_path = ["_templates"]
