/*
 * board.h — the ST NUCLEO-G0B1RE port of the reference firmware: registers, pins and the port's API.
 *
 * The part: STM32G0B1RET6 (Cortex-M0+, up to 64 MHz, 512 KiB flash in two banks of 256 KiB, 144 KiB
 * SRAM; datasheet DS13560 "Description" and "Memory mapping"; reference manual RM0444).
 *
 * Register definitions are written by hand (no vendor header is packaged here). Each block's base
 * address is from RM0444 "Memory map and register boundary addresses" (table "STM32G0x1 peripheral
 * register boundary addresses"); each register offset and bit is from the register description in
 * that block's RM0444 chapter, named below by the chapter's title and the register's name (chapter
 * numbers differ between revisions of RM0444). Every value was cross-checked against ST's CMSIS
 * device header for the part (stm32g0b1xx.h, BSD-3-Clause), from which no code is taken.
 *
 * Pins (NUCLEO-G0B1RE; Arduino names from the board's connector table in UM2324):
 *   USART2  PA2 TX / PA3 RX, AF1          the ST-LINK virtual COM port (one chip on the desk)
 *   USART1  PC4 TX (D1) / PC5 RX (D0), AF1 the sheet's multi-drop bus through an RS-485 transceiver,
 *           PA8 (D7) its driver enable      (DE high only while this chip sends)
 *   SPI1    PA5 SCK (D13), PA6 MISO (D12), PA7 MOSI (D11), AF0; PA5 also lights the user LED LD4
 *           PB0 (D10) chip select 0: the ICM-42688-P;  PB1 (A3) chip select 1: the magnetometer
 *   TIM2    PA0 (A0) TIM2_CH1, AF2: the ICM-42688-P's INT1 (data ready), captured by the timer
 *   FDCAN1  PA11 RX / PA12 TX, AF3 (morpho connector CN10) to a CAN transceiver
 * (alternate-function numbers: DS13560 "Alternate functions" tables, port A, B and C.)
 *
 * Concurrency: the USART RX and FDCAN interrupts are the only ISRs that touch shared data; each
 * writes its own ring (uart.c, can.c) and nothing else. Every capsheet_chip_* call runs in the main
 * loop, never in an ISR (the library is not reentrant; firmware_ref/README.md "Integration rules").
 */
#ifndef CAPSHEET_BOARD_H
#define CAPSHEET_BOARD_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

/* Build options (main.c documents them; firmware_ref/Makefile `board` builds the combinations). */
#ifndef BOARD_TRANSPORT_CAN
#define BOARD_TRANSPORT_CAN 0
#endif
#ifndef BOARD_UART
#define BOARD_UART 2
#endif
#ifndef BOARD_CAN_FD
#define BOARD_CAN_FD 0
#endif
#ifndef BOARD_CAN_FD_DATA_BPS
#define BOARD_CAN_FD_DATA_BPS 8000000u /* 2, 4 or 8 Mbit/s (docs/protocol.md's capacity table: 8) */
#endif
#ifndef BOARD_HSE_HZ
#define BOARD_HSE_HZ 0u       /* 0: HSI16; else an external clock, a multiple of 8 MHz up to 48 MHz */
#endif
#ifndef BOARD_HSE_BYPASS
#define BOARD_HSE_BYPASS 1    /* 1: a clock signal on OSC_IN (the ST-LINK's MCO); 0: a crystal */
#endif

#define REG32(addr) (*(volatile uint32_t *)(uintptr_t)(addr))
#define REG8(addr) (*(volatile uint8_t *)(uintptr_t)(addr))

/* ---- clocks (RM0444 "Reset and clock control (RCC)", "Clocks") -------------------------------- */
/* HSI16 -> PLL: M = 1, N = 8 (VCO 128 MHz), R = 2 -> SYSCLK 64 MHz; AHB and APB undivided.
 * With BOARD_HSE_HZ: HSE -> PLL: M = HSE / 8 MHz, N = 16, R = 2 -> the same 64 MHz, at the external
 * clock's accuracy. DS13560 "General operating conditions": fHCLK and fPCLK up to 64 MHz. */
#define HSI_HZ 16000000u
#define SYSCLK_HZ 64000000u
#define PCLK_HZ 64000000u

/* ---- memory (RM0444 "Embedded flash memory (FLASH)", "FLASH memory organization";
 *      DS13560 "Memory mapping") --------------------------------------------------------------- */
#define FLASH_MEM_BASE 0x08000000u
#define FLASH_MEM_SIZE (512u * 1024u)      /* STM32G0B1xE: 512 KiB (DS13560 "Ordering information") */
#define FLASH_PAGE_SIZE 2048u              /* 2 KiB pages, 64-bit (double-word) programming + 8 ECC bits */
#define FLASH_BANK2_BASE 0x08040000u       /* dual bank: bank 2 is the upper 256 KiB */
#define FLASH_BANK2_FIRST_PNB 256u         /* FLASH_CR PNB numbers bank 2's pages from 256 (with BKER) */
#define SRAM_BASE 0x20000000u
#define SRAM_SIZE (144u * 1024u)           /* DS13560: 144 KiB SRAM (128 KiB of it with parity check) */

/* Calibration storage: the last two pages of bank 2 (linker script: the image ends below them).
 * In bank 2, while the code runs from bank 1: a page erase (22 ms typical, flash.c) does not stall
 * the core or the UART interrupt (read-while-write, DS13560 "Features"). */
#define CAL_PAGE0_ADDR (FLASH_MEM_BASE + FLASH_MEM_SIZE - 2u * FLASH_PAGE_SIZE) /* 0x0807F000 */
#define CAL_PAGE0_PNB (FLASH_BANK2_FIRST_PNB + 126u)
#define CAL_PAGE1_PNB (FLASH_BANK2_FIRST_PNB + 127u)

/* ---- RCC, base 0x4002 1000 (RM0444 "RCC registers") ------------------------------------------- */
#define RCC_BASE 0x40021000u
#define RCC_CR REG32(RCC_BASE + 0x00u)
#define RCC_CR_HSION (1u << 8)
#define RCC_CR_HSIRDY (1u << 10)
#define RCC_CR_HSIDIV_MASK (7u << 11)       /* 000: HSI16 / 1 */
#define RCC_CR_HSEON (1u << 16)
#define RCC_CR_HSERDY (1u << 17)
#define RCC_CR_HSEBYP (1u << 18)
#define RCC_CR_PLLON (1u << 24)
#define RCC_CR_PLLRDY (1u << 25)
#define RCC_CFGR REG32(RCC_BASE + 0x08u)
#define RCC_CFGR_SW_MASK (7u << 0)
#define RCC_CFGR_SW_PLLRCLK (2u << 0)
#define RCC_CFGR_SWS_MASK (7u << 3)
#define RCC_CFGR_SWS_PLLRCLK (2u << 3)
#define RCC_CFGR_HPRE_MASK (0xFu << 8)      /* 0xxx: AHB = SYSCLK */
#define RCC_CFGR_PPRE_MASK (7u << 12)       /* 0xx: APB = HCLK */
#define RCC_PLLCFGR REG32(RCC_BASE + 0x0Cu)
#define RCC_PLLCFGR_PLLSRC_HSI16 (2u << 0)
#define RCC_PLLCFGR_PLLSRC_HSE (3u << 0)
#define RCC_PLLCFGR_PLLM_SHIFT 4u           /* M = PLLM + 1 */
#define RCC_PLLCFGR_PLLN_SHIFT 8u           /* N = PLLN, 8..86 */
#define RCC_PLLCFGR_PLLQEN (1u << 24)
#define RCC_PLLCFGR_PLLQ_SHIFT 25u          /* Q = PLLQ + 1 */
#define RCC_PLLCFGR_PLLREN (1u << 28)
#define RCC_PLLCFGR_PLLR_SHIFT 29u          /* R = PLLR + 1, PLLR >= 1 */
#define RCC_IOPENR REG32(RCC_BASE + 0x34u)
#define RCC_IOPENR_GPIOAEN (1u << 0)
#define RCC_IOPENR_GPIOBEN (1u << 1)
#define RCC_IOPENR_GPIOCEN (1u << 2)
#define RCC_AHBENR REG32(RCC_BASE + 0x38u)
#define RCC_AHBENR_FLASHEN (1u << 8)
#define RCC_APBENR1 REG32(RCC_BASE + 0x3Cu)
#define RCC_APBENR1_TIM2EN (1u << 0)
#define RCC_APBENR1_FDCANEN (1u << 12)
#define RCC_APBENR1_USART2EN (1u << 17)
#define RCC_APBENR1_PWREN (1u << 28)
#define RCC_APBENR2 REG32(RCC_BASE + 0x40u)
#define RCC_APBENR2_SYSCFGEN (1u << 0)
#define RCC_APBENR2_SPI1EN (1u << 12)
#define RCC_APBENR2_USART1EN (1u << 14)
#define RCC_CCIPR REG32(RCC_BASE + 0x54u)   /* USART1SEL bits 1:0, USART2SEL bits 3:2: 00 = PCLK (reset) */
#define RCC_CCIPR2 REG32(RCC_BASE + 0x58u)
#define RCC_CCIPR2_FDCANSEL_MASK (3u << 8)  /* 00: PCLK, 01: PLLQ, 10: HSE */
#define RCC_CCIPR2_FDCANSEL_PCLK (0u << 8)

/* ---- FLASH interface, base 0x4002 2000 (RM0444 "FLASH registers") ----------------------------- */
#define FLASH_R_BASE 0x40022000u
#define FLASH_ACR REG32(FLASH_R_BASE + 0x00u)
#define FLASH_ACR_LATENCY_MASK (7u << 0)
#define FLASH_ACR_LATENCY_2WS (2u << 0)     /* HCLK > 48 MHz in range 1: two wait states
                                             * (RM0444 "Read access latency", table of wait states) */
#define FLASH_ACR_PRFTEN (1u << 8)
#define FLASH_ACR_ICEN (1u << 9)
#define FLASH_KEYR REG32(FLASH_R_BASE + 0x08u)
#define FLASH_KEY1 0x45670123u              /* "Unlocking the Flash memory": KEY1 then KEY2 */
#define FLASH_KEY2 0xCDEF89ABu
#define FLASH_SR REG32(FLASH_R_BASE + 0x10u)
#define FLASH_SR_EOP (1u << 0)
#define FLASH_SR_OPERR (1u << 1)
#define FLASH_SR_PROGERR (1u << 3)
#define FLASH_SR_WRPERR (1u << 4)
#define FLASH_SR_PGAERR (1u << 5)
#define FLASH_SR_SIZERR (1u << 6)
#define FLASH_SR_PGSERR (1u << 7)
#define FLASH_SR_MISERR (1u << 8)
#define FLASH_SR_FASTERR (1u << 9)
#define FLASH_SR_RDERR (1u << 14)
#define FLASH_SR_OPTVERR (1u << 15)
#define FLASH_SR_BSY1 (1u << 16)
#define FLASH_SR_BSY2 (1u << 17)
#define FLASH_SR_CFGBSY (1u << 18)
#define FLASH_SR_ERRORS (FLASH_SR_OPERR | FLASH_SR_PROGERR | FLASH_SR_WRPERR | FLASH_SR_PGAERR | FLASH_SR_SIZERR | \
                         FLASH_SR_PGSERR | FLASH_SR_MISERR | FLASH_SR_FASTERR | FLASH_SR_RDERR | FLASH_SR_OPTVERR)
#define FLASH_CR REG32(FLASH_R_BASE + 0x14u)
#define FLASH_CR_PG (1u << 0)
#define FLASH_CR_PER (1u << 1)
#define FLASH_CR_PNB_SHIFT 3u               /* PNB bits 12:3 */
#define FLASH_CR_PNB_MASK (0x3FFu << 3)
#define FLASH_CR_BKER (1u << 13)            /* the page to erase is in bank 2 */
#define FLASH_CR_STRT (1u << 16)
#define FLASH_CR_LOCK (1u << 31)

/* ---- GPIO, IOPORT bus, base 0x5000 0000 + 0x400 per port (RM0444 "GPIO registers") ------------ */
#define GPIOA_BASE 0x50000000u
#define GPIOB_BASE 0x50000400u
#define GPIOC_BASE 0x50000800u
#define GPIO_MODER(p) REG32((p) + 0x00u)    /* 2 bits per pin: 00 in, 01 out, 10 alternate, 11 analog */
#define GPIO_OTYPER(p) REG32((p) + 0x04u)
#define GPIO_OSPEEDR(p) REG32((p) + 0x08u)  /* 2 bits per pin: 11 very high speed */
#define GPIO_PUPDR(p) REG32((p) + 0x0Cu)    /* 2 bits per pin: 01 pull-up, 10 pull-down */
#define GPIO_IDR(p) REG32((p) + 0x10u)
#define GPIO_BSRR(p) REG32((p) + 0x18u)     /* bits 15:0 set, bits 31:16 reset */
#define GPIO_AFRL(p) REG32((p) + 0x20u)     /* 4 bits per pin, pins 0..7 */
#define GPIO_AFRH(p) REG32((p) + 0x24u)     /* pins 8..15 */
#define GPIO_MODE_OUT 1u
#define GPIO_MODE_AF 2u

/* ---- TIM2 (32-bit), base 0x4000 0000 (RM0444 "General-purpose timers (TIM2/TIM3/TIM4)") ------- */
#define TIM2_BASE 0x40000000u
#define TIM2_CR1 REG32(TIM2_BASE + 0x00u)
#define TIM_CR1_CEN (1u << 0)
#define TIM2_SR REG32(TIM2_BASE + 0x10u)
#define TIM_SR_CC1IF (1u << 1)
#define TIM_SR_CC1OF (1u << 9)
#define TIM2_EGR REG32(TIM2_BASE + 0x14u)
#define TIM_EGR_UG (1u << 0)                /* reload the prescaler now (it is preloaded) */
#define TIM2_CCMR1 REG32(TIM2_BASE + 0x18u)
#define TIM_CCMR1_CC1S_TI1 (1u << 0)        /* CC1 is an input, IC1 on TI1 */
#define TIM_CCMR1_IC1F_SHIFT 4u             /* input filter, 0000: none */
#define TIM2_CCER REG32(TIM2_BASE + 0x20u)
#define TIM_CCER_CC1E (1u << 0)
#define TIM_CCER_CC1P (1u << 1)             /* with CC1NP = 0: 0 rising edge, 1 falling edge */
#define TIM2_CNT REG32(TIM2_BASE + 0x24u)
#define TIM2_PSC REG32(TIM2_BASE + 0x28u)
#define TIM2_ARR REG32(TIM2_BASE + 0x2Cu)
#define TIM2_CCR1 REG32(TIM2_BASE + 0x34u)

/* ---- USART1 0x4001 3800, USART2 0x4000 4400 (RM0444 "Universal synchronous/asynchronous receiver
 *      transmitter (USART/UART)", "USART registers"; FIFO mode registers) ------------------------ */
#define USART1_BASE 0x40013800u
#define USART2_BASE 0x40004400u
#define USART_CR1(b) REG32((b) + 0x00u)
#define USART_CR1_UE (1u << 0)
#define USART_CR1_RE (1u << 2)
#define USART_CR1_TE (1u << 3)
#define USART_CR1_RXFNEIE (1u << 5)         /* RXNEIE / RXFNEIE: RX FIFO not empty interrupt */
#define USART_CR1_OVER8 (1u << 15)          /* oversampling by 8: baud = 2 fck / USARTDIV, up to fck / 8 */
#define USART_CR1_FIFOEN (1u << 29)
#define USART_CR3(b) REG32((b) + 0x08u)
#define USART_CR3_EIE (1u << 0)             /* error interrupt (framing, noise, overrun) in FIFO mode */
#define USART_BRR(b) REG32((b) + 0x0Cu)
#define USART_ISR(b) REG32((b) + 0x1Cu)
#define USART_ISR_PE (1u << 0)
#define USART_ISR_FE (1u << 1)
#define USART_ISR_NE (1u << 2)
#define USART_ISR_ORE (1u << 3)
#define USART_ISR_RXFNE (1u << 5)           /* RXNE / RXFNE */
#define USART_ISR_TC (1u << 6)
#define USART_ISR_TXFNF (1u << 7)           /* TXE / TXFNF */
#define USART_ICR(b) REG32((b) + 0x20u)     /* write 1 to clear: PECF 0, FECF 1, NECF 2, ORECF 3 */
#define USART_ICR_ERRORS 0xFu
#define USART_RDR(b) REG32((b) + 0x24u)
#define USART_TDR(b) REG32((b) + 0x28u)

/* ---- SPI1, base 0x4001 3000 (RM0444 "Serial peripheral interface / integrated interchip sound
 *      (SPI/I2S)", "SPI registers") ------------------------------------------------------------- */
#define SPI1_BASE 0x40013000u
#define SPI1_CR1 REG32(SPI1_BASE + 0x00u)
#define SPI_CR1_CPHA (1u << 0)
#define SPI_CR1_CPOL (1u << 1)
#define SPI_CR1_MSTR (1u << 2)
#define SPI_CR1_BR_SHIFT 3u                 /* fPCLK / 2^(BR + 1) */
#define SPI_CR1_SPE (1u << 6)
#define SPI_CR1_SSI (1u << 8)
#define SPI_CR1_SSM (1u << 9)
#define SPI1_CR2 REG32(SPI1_BASE + 0x04u)
#define SPI_CR2_DS_8BIT (7u << 8)           /* DS = 0111: 8-bit frames */
#define SPI_CR2_FRXTH (1u << 12)            /* RXNE at 8 bits in the RX FIFO */
#define SPI1_SR REG32(SPI1_BASE + 0x08u)
#define SPI_SR_RXNE (1u << 0)
#define SPI_SR_TXE (1u << 1)
#define SPI_SR_MODF (1u << 5)
#define SPI_SR_OVR (1u << 6)
#define SPI_SR_BSY (1u << 7)
#define SPI_SR_FRLVL_MASK (3u << 9)
#define SPI1_DR8 REG8(SPI1_BASE + 0x0Cu)    /* a byte access: one 8-bit frame (a word access packs two) */

/* ---- FDCAN1, base 0x4000 6400; its message RAM at 0x4000 B400 (RM0444 "FD controller area network
 *      (FDCAN)", "FDCAN registers" and "Message RAM"). The message RAM's layout is fixed on this part:
 *      28 standard filters (1 word), 8 extended filters (2 words), Rx FIFO 0 and 1 of 3 elements, a
 *      Tx event FIFO of 3 (2 words) and 3 Tx buffers, each Rx/Tx element 18 words (64 data bytes). */
#define FDCAN1_BASE 0x40006400u
#define FDCAN_CONFIG_BASE 0x40006500u
#define FDCAN_CKDIV REG32(FDCAN_CONFIG_BASE + 0x00u) /* PDIV bits 3:0: 0000 = kernel clock / 1 */
#define FDCAN_DBTP REG32(FDCAN1_BASE + 0x00Cu)    /* DSJW 3:0, DTSEG2 7:4, DTSEG1 12:8, DBRP 20:16, TDC 23 */
#define FDCAN_DBTP_TDC (1u << 23)
#define FDCAN_CCCR REG32(FDCAN1_BASE + 0x018u)
#define FDCAN_CCCR_INIT (1u << 0)
#define FDCAN_CCCR_CCE (1u << 1)
#define FDCAN_CCCR_FDOE (1u << 8)
#define FDCAN_CCCR_BRSE (1u << 9)
#define FDCAN_NBTP REG32(FDCAN1_BASE + 0x01Cu)    /* NTSEG2 6:0, NTSEG1 15:8, NBRP 24:16, NSJW 31:25 */
#define FDCAN_ECR REG32(FDCAN1_BASE + 0x040u)
#define FDCAN_PSR REG32(FDCAN1_BASE + 0x044u)
#define FDCAN_PSR_BO (1u << 7)                    /* bus off */
#define FDCAN_TDCR REG32(FDCAN1_BASE + 0x048u)    /* TDCF 6:0, TDCO 14:8 */
#define FDCAN_IR REG32(FDCAN1_BASE + 0x050u)      /* write 1 to clear */
#define FDCAN_IR_RF0N (1u << 0)                   /* Rx FIFO 0 new message */
#define FDCAN_IR_RF0L (1u << 2)                   /* Rx FIFO 0 message lost */
#define FDCAN_IE REG32(FDCAN1_BASE + 0x054u)
#define FDCAN_ILE REG32(FDCAN1_BASE + 0x05Cu)
#define FDCAN_ILE_EINT0 (1u << 0)
#define FDCAN_RXGFC REG32(FDCAN1_BASE + 0x080u)   /* RRFE 0, RRFS 1, ANFE 3:2, ANFS 5:4, LSS 20:16, LSE 27:24 */
#define FDCAN_RXGFC_RRFE (1u << 0)
#define FDCAN_RXGFC_RRFS (1u << 1)
#define FDCAN_RXGFC_ANFE_REJECT (2u << 2)
#define FDCAN_RXGFC_ANFS_REJECT (2u << 4)
#define FDCAN_RXGFC_LSE_SHIFT 24u
#define FDCAN_RXF0S REG32(FDCAN1_BASE + 0x090u)   /* F0FL 3:0, F0GI 9:8 */
#define FDCAN_RXF0A REG32(FDCAN1_BASE + 0x094u)
#define FDCAN_TXFQS REG32(FDCAN1_BASE + 0x0C4u)   /* TFQPI 17:16, TFQF 21 */
#define FDCAN_TXFQS_TFQF (1u << 21)
#define FDCAN_TXBAR REG32(FDCAN1_BASE + 0x0CCu)
#define SRAMCAN_BASE 0x4000B400u                  /* FDCAN1's message RAM; FDCAN2's follows at +0x350 */
#define SRAMCAN_FLESA 0x070u                      /* extended filters */
#define SRAMCAN_RF0SA 0x0B0u                      /* Rx FIFO 0 */
#define SRAMCAN_TFQSA 0x278u                      /* Tx buffers */
#define SRAMCAN_SIZE 0x350u
#define SRAMCAN_ELEMENT_SIZE 72u                  /* 18 words */

/* ---- Unique device ID, 96 bits at 0x1FFF 7590 (RM0444 "Device electronic signature",
 *      "Unique device ID register (96 bits)") --------------------------------------------------- */
#define UID_BASE 0x1FFF7590u

/* ---- Cortex-M0+ core (Armv6-M ARM, B3.4 NVIC; B3.3 SysTick) ------------------------------------ */
#define NVIC_ISER REG32(0xE000E100u)
#define SYST_CSR REG32(0xE000E010u)
#define SYST_RVR REG32(0xE000E014u)
#define SYST_CVR REG32(0xE000E018u)

/* IRQ numbers (RM0444 "Nested vectored interrupt controller (NVIC)", vector table) */
#define IRQ_TIM16_FDCAN1 21u
#define IRQ_USART1 27u
#define IRQ_USART2 28u

#define STACK_PAINT 0xDEADBEEFu

/* ---- the port's API ----------------------------------------------------------------------------- */

/* gpio.c: one pin as an alternate function / output. */
void gpio_af(uint32_t port, unsigned pin, unsigned af);
void gpio_out(uint32_t port, unsigned pin, bool high);
void gpio_write(uint32_t port, unsigned pin, bool high);

/* clock.c: HSI16 (or HSE) -> PLL -> 64 MHz, TIM2 at 1 MHz as the time base, SysTick 1 kHz to wake
 * from WFI. With BOARD_HSE_HZ, false when the external clock never became ready (the port then runs
 * on HSI16, out of CAN's clock tolerance: see can.c). */
bool clock_init(void);
/* Microseconds since clock_init, TIM2's 32-bit count extended to 64 bits. Main loop only (at least
 * once every 71 minutes, which the loop does). */
uint64_t clock_us(void);
/* The last INT1 edge TIM2 captured on PA0 since the previous call, on clock_us's time base: true and
 * *edge_us set, or false (no edge). *missed counts edges captured over an unread one. Main loop only. */
bool clock_capture(uint64_t *edge_us, uint32_t *missed);
void systick_irq(void);

/* uart.c: the serial transport. RX interrupt into a ring; blocking TX (driver enable around it). */
#define UART_RX_RING_SIZE 1024u             /* a power of two */
void uart_init(uint32_t baud);
/* Copy up to `cap` received bytes out of the RX ring; returns how many (0 if none). */
size_t uart_read(uint8_t *out, size_t cap);
/* Bytes wait in the RX ring (main loop, with interrupts masked before a WFI). */
bool uart_pending(void);
/* Blocking write: returns once the last byte's stop bit is on the wire (the RS-485 driver is then
 * released), so `data` may be reused at once. */
void uart_write(const uint8_t *data, size_t len);
/* Reception losses since boot: a byte dropped because the ring was full, or a UART overrun, framing,
 * noise or parity error (one count each). The chip's stream decoder also counts the frames they
 * broke (rx_errors in STATUS). */
uint32_t uart_lost(void);
void usart_irq(void);

/* spi.c: SPI1 master, mode 3, 8 MHz, two chip selects (0: ICM-42688-P on PB0, 1: magnetometer on PB1).
 * One full-duplex transaction with the chip select held low. 0, or -1 for a bad chip select / length,
 * -2 for a bus fault (mode fault, overrun, a transfer that did not finish). */
#define SPI_CS_IMU 0u
#define SPI_CS_MAG 1u
void spi_init(void);
int32_t spi_transfer(uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len);

/* flash.c: the two calibration pages in bank 2. 0, or negative: the FLASH_SR error bits, negated;
 * -1 for an address or page outside the calibration pages (the image is never touched). */
int32_t flash_erase_page(uint32_t pnb);
int32_t flash_program_dword(uint32_t addr, uint32_t lo, uint32_t hi);

/* can.c: FDCAN1, classic CAN at 1 Mbit/s, 29-bit identifiers; with BOARD_CAN_FD, FD frames with bit-
 * rate switching at BOARD_CAN_FD_DATA_BPS in the data phase. Every received data frame goes to a ring
 * (ISR); the chip library decides which are its own. */
typedef struct {
    uint32_t id;
    bool is_extended;
    uint8_t len;
    bool is_fd;
    uint8_t data[64];
} can_frame_t;
void can_init(void);
bool can_read(can_frame_t *out);
bool can_pending(void);
/* Queue one frame: 0, or -1 when the three Tx buffers stay full for 1 ms (a bus with no other node to
 * acknowledge, or bus-off), -2 for a length over 8 (64 with FD). */
int32_t can_write(uint32_t id, const uint8_t *data, uint8_t len, bool is_fd);
uint32_t can_lost(void);
void fdcan1_irq(void);

#endif
