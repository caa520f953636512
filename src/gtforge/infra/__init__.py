"""Ground floor: atomic and unbuffered writes, hashing, scheduling and worker pools; imports nothing of gtforge but \
errors."""
