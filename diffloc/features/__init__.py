"""Local and global image features, descriptor matching and retrieval."""
