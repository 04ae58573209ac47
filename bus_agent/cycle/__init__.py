"""The cyclic loop and what runs beside it in the cycle process: the cycle thread
(:mod:`.cycle`, which owns its parts: :mod:`.timing`, :mod:`.stats`, :mod:`.slaves`,
:mod:`.outcomes`, :mod:`.commands`, :mod:`.nmt`, :mod:`.reflexes`, :mod:`.controllers`,
:mod:`.motion`, :mod:`.output`, :mod:`.startup`), the management thread (:mod:`.management`),
group membership (:mod:`.groups`) and real-time thread settings (:mod:`.realtime`)."""
