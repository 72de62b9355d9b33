"""What avatars read: MPEG-4 FAPs and .fap files, ARKit blendshapes."""
