"""The cyclic loop and what runs beside it in the cycle process: the cycle thread
(:mod:`.cycle`), the management thread (:mod:`.management`), group membership (:mod:`.groups`)
and real-time thread settings (:mod:`.realtime`)."""
