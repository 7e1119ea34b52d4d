"""placeholder"""
def add_render_command(sub):
    pass
