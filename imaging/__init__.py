"""The foundation every other package builds on: errors, atomic writes, image files (EXR, PNG,
PFM/HDR), Mitsuba backend selection and the render core, metrics, tiling, hashing, and the pieces
every command shares (one-line usage errors, the progress-bar protocol). It imports no other
package of this project (tests/test_layers.py)."""
