"""One bridge chip's hardware as plain objects: counters, oscillator, ADC and their noise."""
