"""The learned single-frame lift's weights and the script that trains them (see :mod:`reconstruction.monocular.lifter`)."""
