"""Training of our networks, apart from the runtime stages that run them: the attention detector (``detector``,
its loss, data and labelled photos, copy-paste and pseudo-label augmentation, the FastestDet and BlazePose
teachers), YOLOX-nano fine-tuning and its mask head (``yolox``, ``yolox_masks``), ConvPoint keypoints
(``keypoints`` on synthetic ``shapes`` and real frames) and the VLADNet place descriptor (``place``).

Every trainer is seeded, resumes from its last checkpoint and runs at toy scale in the tests; ``vslam train ...``
(``vslam.cli.train``) is the command line over them. Modules import torch, numpy and cv2, not the SLAM stack.
"""
