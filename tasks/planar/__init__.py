"""What the planar pushing tasks share: the PD-controlled disc agent in the walled 512 px workspace, its stepping
loop, approach-path following, the OpenCV drawing helpers and colours, the recording loop of scripted episodes, and
the true simulator as a world model.

Push-T, Cube & Sphere Swapping and Triangle Drawing (its agent a pen) import it; each keeps its own objects, reward and
observation.
"""
