"""Networks: one base model, one registry per family, one checkpoint format, one device rule, one ops module.

- ``base``: ``BaseModel`` (default conf merged with the caller's; dict in, dict out).
- ``registry``: ``DETECTORS``, ``KEYPOINTS``, ``PLACES``: a network by name from a config; public weights
  converted by ``weights/<source>.py``.
- ``checkpoint``: ``save_model`` / ``load_model`` (``{arch, conf, state_dict, meta}``), weights-only reading.
- ``device``: ``pick_device``; ``ops``: box IoU and NMS.

Importing this package imports no torch; the modules that need it import it themselves.
"""
