"""The studies built on runs: the paper's cases side by side (:mod:`.reproduce`), adaptation, learning and
diagnosis of the noise model and their calibration, soak and the sine benchmark."""
