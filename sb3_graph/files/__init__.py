"""Files that come from other people, read without running their code: weights-only policy files,
signed checkpoints, rl-zoo3 experiment files and the Python-valued strings in them, checked policy
keyword arguments, and output folders that are whole or absent."""
