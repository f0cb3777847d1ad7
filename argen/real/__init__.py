"""Recorded RGB-D data: reading a recording folder (:mod:`.recording`), the AR capture into a recording's frames
(:mod:`.capture`), and replacing objects in existing test scenes (:mod:`.replace`)."""
