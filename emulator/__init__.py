"""emulator layer of cellbridge (see DESIGN.md); filled in by later work."""
