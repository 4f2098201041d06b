"""The omnidirectional ToF sensor as a physical object: ToF decoding of the four samples (`tof`,
paper eq. 1–4), the camera with its lens (`camera`), planar mirrors and their virtual cameras
(`mirrors`, eq. 5–6), the whole rig with its one YAML form (`rig`), and the choice of the
default rig from a sweep of designs (`design`). Nothing here reads or writes files or draws:
files are in `omnitof.io`, figures in `omnitof.viz`."""
