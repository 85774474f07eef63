"""maem-calibrate (``calibrate`` dispatches to ``calibrate_people``: from the players, with its
report ``calibrate_report``, and ``calibrate_board``: from a ChArUco or checkerboard) and
maem-calib-bench (``calib_bench``: people calibration against simulated true rigs)."""
