"""The version of both distributions built from this repository (edgefeat and edgefeat-runtime).

Read by both pyproject files (setuptools' attr: reads it without importing the package), by `toolkit
--version`, and stamped as ``toolkit_version`` into every artefact manifest export and quantise write.
Every change a user can see gets a line in CHANGELOG.md under the version it ships in.
"""

__version__ = "0.2.0"
