"""The add-on's one user-facing exception. No ``bpy`` here."""


class UserError(ValueError):
    """Something the user can fix; the message says what, and nothing was changed."""
