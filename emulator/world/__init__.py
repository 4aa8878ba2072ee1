"""What presses on the skin, and each element's capacitance."""
