"""The cross-view pair gates of MAEM stage 2: bbox-centre reprojection and the dense-mesh epipolar
distance, with their numba kernels (``epipolar``, ``epipolar_kernel``, ``reprojection_kernel``)."""
