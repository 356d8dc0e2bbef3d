"""Sphinx configuration."""

project = "rcvae_torchrl"
author = "rcvae_torchrl developers"
extensions = ["sphinx.ext.autodoc", "sphinx.ext.napoleon", "sphinx.ext.mathjax"]
autodoc_member_order = "bysource"
autodoc_typehints = "description"
napoleon_google_docstring = True
html_theme = "alabaster"
html_static_path = ["_static"]
exclude_patterns = ["_build"]
nitpicky = False
napoleon_use_ivar = True

# Docstrings write a batch's size as |B| (e.g. "N·|B| trajectories"), which reStructuredText
# reads as a substitution reference: define it as the literal text.
rst_prolog = r"""
.. |B| replace:: \|B\|
"""
