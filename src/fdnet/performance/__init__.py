"""Speed, measured against references taken in the same run (``fdnet benchmark``): descriptor
extraction through the descriptor interface and FDNet's own paths, matching and faiss indexes at
scale, and the loop-closure detector; above the methods and stages it times."""
