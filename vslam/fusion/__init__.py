"""Navigation fusion and data reliability (seeds 000, 002, 003 ch. 2, 004).

filters (EKF, CKF, SR-CKF, adaptive robust MCC SR-CKF), ins_gnss + simulate (tightly coupled
INS/GNSS), validity (limit values, priority mode), identification (hypothesis bank),
multi_vehicle (vector KF vs two-stage), experiments (reports + CLI).
"""
