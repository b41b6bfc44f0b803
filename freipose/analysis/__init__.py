"""Behavioral variables from poses and attribution of stimulation effects to body parts."""
