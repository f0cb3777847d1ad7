"""The simulated AR capture, in the order a frame passes through it: the marker board (:mod:`.board`), the scene
(:mod:`.placement`, :mod:`.scene`), the view (:mod:`.camera`), rendering (:mod:`.render`), the AR step that
estimates the camera from the markers and composites the objects (:mod:`.ar`), the depth sensor's noise
(:mod:`.noise`), and the capture loop that writes BOP scenes (:mod:`.capture`)."""
