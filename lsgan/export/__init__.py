"""Export motions for other tools: animated GLB (glb.py) and BVH (bvh.py)."""
