"""Skeletons and skinning: a joint tree from a solid (curve skeleton) or from a dynamic mesh (rigid parts of
its motion), linear-blend-skinning weights fitted to the sequence, and UsdSkel / glTF-skin exports."""
