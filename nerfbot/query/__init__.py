"""What a robot asks a trained model: images, depth, meshes, joint angles (docs/ARCHITECTURE.md)."""
