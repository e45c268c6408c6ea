"""Human in the loop: a person drives the ego on the rendered camera view (`vcfusion drive`).

inputs.py     control devices (keyboard, SDL joystick / wheel with an axis map, replay of a file)
              -> one ControlSample per SUMO step
calibration.py  axis maps: wheel presets, `vcfusion drive --calibrate`, the axis-map file
vehicle.py    the ego's vehicle model: pedals -> acceleration, steering -> yaw and lateral position
sdl.py        pygame / SDL set-up (hints) and SDL's virtual joystick (tests, bench)
display.py    the window: camera render + AR overlay re-projected every frame, HUD, screens, video
driver.py     HumanDriver: the ego controller that paces the loop to the wall clock, reads the
              device every step, shows frames and records inputs / frames
drive.py      one trip: wire the run, drive it, write the run folder; the wheel calibration
study.py      a participant's session: practice, counterbalanced paired trips, pause screens, SSQ
"""
