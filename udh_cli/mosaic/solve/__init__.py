"""From pairs to one plane per part: chaining, loop closure, the global solve (homographies or cameras), rectification."""
