"""Objects: BOP models folders and built-in stand-ins (:mod:`.objects`), importing any mesh as a BOP models folder
(:mod:`.meshimport`), and finding an object's symmetries (:mod:`.symmetry`)."""
