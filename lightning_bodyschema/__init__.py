"""lightning_bodyschema: learn and adapt the body schema of musculoskeletal robots."""
__version__ = "0.1.0"
