"""Real faces: face detection, landmarks and enrolment of a speaker from a video clip."""
