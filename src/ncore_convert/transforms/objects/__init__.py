"""Objects: the box-geometry kernel (boxes), which tracks move and which points lie on them
(dynamic), and class names (classes)."""
