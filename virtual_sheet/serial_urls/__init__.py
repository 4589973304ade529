"""pyserial URL handlers for the virtual sheet's devices (``serial.protocol_handler_packages``):
``memory://NAME`` opens an in-memory link published with `virtual_sheet.memport.publish`."""
