"""The one exception type for bad input: its message is the single line a user sees."""


class InputError(ValueError):
    """Bad input, described in one line naming the file, row/field and the problem."""

    def __init__(self, where: str, problem: str):
        super().__init__(f"{where}: {problem}")
        self.where = where
        self.problem = problem
