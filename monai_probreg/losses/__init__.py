"""See the package docstring for the shared conventions."""
