"""Watching a run: ``rerun_log`` streams each frame to Rerun (a viewer, a web viewer or an .rrd file).

Optional (``pip install 'vslam[viewer]'``): nothing here imports ``rerun`` until a logger is made.
"""
