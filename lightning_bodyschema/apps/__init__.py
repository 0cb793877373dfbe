"""Applications built on the library: the paper reproduction, the case-file and request-file tools, the dataset
tool. ``tools/*.py`` are thin wrappers around them. The library (``sim``, ``faults``, ``samplers``, ``networks``,
``schemas``, ``evaluation``) never imports this package."""
