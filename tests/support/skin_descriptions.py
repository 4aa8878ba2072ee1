"""Skin descriptions the tests share (a test file imports no other test file)."""

#: Two links (torso, forearm): a cylinder band around the forearm with a wrap seam, and two
#: chest patches side by side on the torso.
SKIN = """
name = "test"
side = 0.04
[[link]]
name = "torso"
[[link]]
name = "forearm"
parent = "torso"
origin = [0.3, 0.0, 0.0]
rpy = [0.0, 1.5707963267948966, 0.0]

[[patch]]
name = "fore"
link = "forearm"
shape = "cylinder"
radius = 0.045
wrap = true
rows = 3
cols = 7
origin = [0.0, 0.0, 0.05]

[[patch]]
name = "chest_l"
link = "torso"
shape = "plane"
rows = 2
cols = 2
origin = [0.0, 0.0, 0.1]

[[patch]]
name = "chest_r"
link = "torso"
shape = "plane"
rows = 2
cols = 2
origin = [0.08, 0.0, 0.1]

[[gateway]]
name = "arm"
patch = "fore"
[[gateway]]
name = "chest"
patch = "chest_l"
"""
