"""Key: silhouettes from camera images (chroma, difference, threshold keys; clean-up; consensus; GrabCut)."""
